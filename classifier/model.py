"""The network: a torchvision ResNet whose forward pass returns penultimate features and logits.

torchvision is imported through :func:`nerfmeta.compat.import_torchvision` (its compiled ops
cannot load beside the CPU build of torch; the ResNet builders are pure Python).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from nerfmeta.compat import import_torchvision
from nerfmeta.errors import ConfigError

from classifier.config import ARCHITECTURES, STEMS


class SceneNet(nn.Module):
    """A torchvision ResNet (``self.net``) returning ``(features, logits)``.

    The state dict keys are torchvision's with a ``net.`` prefix, so a torchvision checkpoint
    loads with :func:`load_pretrained`.
    """

    def __init__(self, arch: str, num_classes: int, stem: str = "imagenet"):
        super().__init__()
        if arch not in ARCHITECTURES:
            raise ConfigError(f"architecture {arch!r}: expected one of {', '.join(ARCHITECTURES)}")
        if stem not in STEMS:
            raise ConfigError(f"stem {stem!r}: expected one of {', '.join(STEMS)}")
        tv = import_torchvision()
        self.net = getattr(tv.models, arch)(weights=None, num_classes=num_classes)
        if stem != "imagenet":
            # small inputs: a 3x3 conv (stride 2 or 1) and no max-pool keep 4x or 16x more positions
            stride = 2 if stem == "3x3s2" else 1
            self.net.conv1 = nn.Conv2d(3, 64, kernel_size=3, stride=stride, padding=1, bias=False)
            nn.init.kaiming_normal_(self.net.conv1.weight, mode="fan_out", nonlinearity="relu")
            self.net.maxpool = nn.Identity()
        self.arch = arch
        self.num_classes = num_classes
        self.stem = stem

    @property
    def feature_dim(self) -> int:
        return int(self.net.fc.in_features)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """images: (B, 3, S, S) normalised -> features (B, feature_dim), logits (B, num_classes)."""
        n = self.net
        x = n.maxpool(n.relu(n.bn1(n.conv1(images))))
        x = n.layer4(n.layer3(n.layer2(n.layer1(x))))
        features = torch.flatten(n.avgpool(x), 1)
        return features, n.fc(features)


def build_model(arch: str, num_classes: int, *, stem: str = "imagenet", seed: int = 0) -> SceneNet:
    """A freshly initialised :class:`SceneNet`, its weights a function of ``seed`` only.

    The initialisation draws from a forked copy of torch's global generator, so the caller's
    random state is left as it was.
    """
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return SceneNet(arch, num_classes, stem)


def empty_model(arch: str, num_classes: int, *, stem: str = "imagenet") -> SceneNet:
    """A :class:`SceneNet` with uninitialised parameters on the meta device (no init cost).

    Fill it with ``model.load_state_dict(state, assign=True)``.
    """
    with torch.device("meta"):
        return SceneNet(arch, num_classes, stem)


def load_pretrained(model: SceneNet, path: str | os.PathLike) -> list[str]:
    """Copy a user's local pretrained weights into ``model``, skipping the ``fc`` layer.

    Accepts a torchvision ResNet state dict (keys like ``layer1.0.conv1.weight``) or one saved
    from a :class:`SceneNet` (``net.`` prefix), as safetensors or a ``torch.save`` file (read with
    ``weights_only=True``). With a 3x3 ``stem`` the 7x7 stem weights do not fit and are skipped too.

    Returns:
        the names of the parameters left at their fresh initialisation.

    Raises:
        ConfigError: the file is missing or unreadable, or shares no tensor with the model.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"--weights {path}: file not found")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # safetensors and torch raise many types for a bad file
        raise ConfigError(f"--weights {path}: cannot read as safetensors or a torch state dict ({type(err).__name__})") from err
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ConfigError(f"--weights {path}: expected a state dict, got {type(state).__name__}")
    own = model.net.state_dict()
    loaded = {}
    for key, value in state.items():
        name = key[len("net."):] if key.startswith("net.") else key
        name = name[len("module."):] if name.startswith("module.") else name
        if name.startswith("fc.") or name not in own or not isinstance(value, torch.Tensor):
            continue
        if tuple(value.shape) != tuple(own[name].shape):
            continue
        loaded[name] = value
    if not loaded:
        raise ConfigError(f"--weights {path}: no tensor matches a {model.arch} backbone (is it a {model.arch} state dict?)")
    model.net.load_state_dict(loaded, strict=False)
    return sorted(k for k in own if k not in loaded)
