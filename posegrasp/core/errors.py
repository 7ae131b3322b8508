"""Exception tree of posegrasp: one base class, messages that name the valid choices."""

from __future__ import annotations

from collections.abc import Iterable


class PosegraspError(Exception):
    """Base class of every error posegrasp raises on purpose."""


class UnknownNameError(PosegraspError, ValueError):
    """A name (object, joint, camera, estimator ...) that is not one of the valid choices."""

    def __init__(self, kind: str, name: str, choices: Iterable[str]) -> None:
        choices = list(choices)
        super().__init__(f"unknown {kind} {name!r}; valid {kind}s: {', '.join(choices)}")
        self.kind = kind
        self.name = name
        self.choices = choices


class InvalidArgumentError(PosegraspError, ValueError):
    """An argument outside its valid range (negative resolution, non-finite pose ...)."""


class AssetError(PosegraspError, RuntimeError):
    """A required asset (robot model, weights, data) is missing or corrupt."""


class StateError(PosegraspError, RuntimeError):
    """An object used out of order (a step before a reset, an episode acted on twice ...)."""
