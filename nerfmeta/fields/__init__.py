"""Backbones: every one is a :class:`~nerfmeta.fields.base.RadianceModel`."""
