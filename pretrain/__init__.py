"""Starting points for fits: category models and meta-learned initialisations.

- :mod:`pretrain.category`: ``nerfmeta pretrain category`` trains one field on all training scenes
  of a category (its mean shape and appearance) and saves it with :func:`nerfmeta.init.save_init`
  (kind ``category``); ``nerfmeta fit SCENE --init category:DIR --freeze K`` fine-tunes it.
- ``pretrain.meta*``: ``nerfmeta meta-train`` learns an initialisation across categories (kind
  ``meta``); ``nerfmeta fit SCENE --init meta:DIR`` starts from it.

See README.md in this folder. Nothing is imported here, so importing one part does not load the other.
"""
