"""The ResNet scene classifier with an "unknown" answer (``nerfmeta classifier train``, ``nerfmeta classify``).

- :mod:`classifier.config`: :class:`TrainConfig` and :class:`AugmentConfig` (frozen, saved as JSON).
- :mod:`classifier.data`: views as premultiplied RGBA, augmentations, the training :class:`ViewSet`.
- :mod:`classifier.inputs`: what ``classify`` reads (scene folders, image folders, single images).
- :mod:`classifier.model`: the torchvision ResNet returning features and logits.
- :mod:`classifier.predict`: pure functions: view-averaged softmax, unknown scores, threshold decision.
- :mod:`classifier.train`: training, calibration on validation scenes, the output folder.
- :mod:`classifier.store`: saving, loading (hash-checked) and applying a classifier folder.
"""

from classifier.config import AugmentConfig, TrainConfig
from classifier.inputs import read_scene_views
from classifier.predict import FeatureStats, Prediction, decide, scene_probabilities
from classifier.store import Classifier, ClassifierError, classify_views, load_classifier, save_classifier
from classifier.train import train_classifier

__all__ = [
    "AugmentConfig",
    "Classifier",
    "ClassifierError",
    "FeatureStats",
    "Prediction",
    "TrainConfig",
    "classify_views",
    "decide",
    "load_classifier",
    "read_scene_views",
    "save_classifier",
    "scene_probabilities",
    "train_classifier",
]
