"""The optional extra ``peers``: which of its libraries are installed, and the one-line error
that says how to install them."""

from __future__ import annotations

import importlib
import importlib.util

from posegrasp.core.errors import AssetError

#: How the extra installs (`make setup` installs it too).
INSTALL_HINT = "pip install -e '.[peers]' (make setup installs it)"


def has_ppf() -> bool:
    """Whether OpenCV's contrib module ``ppf_match_3d`` is there (``opencv-contrib-python``)."""
    if importlib.util.find_spec("cv2") is None:
        return False
    return hasattr(importlib.import_module("cv2"), "ppf_match_3d")


def has_open3d() -> bool:
    """Whether Open3D imports."""
    if importlib.util.find_spec("open3d") is None:
        return False
    try:
        importlib.import_module("open3d")
    except (ImportError, OSError):  # a wheel without its system library (libusb)
        return False
    return True


def require(estimator: str, ppf: bool = False, open3d: bool = False) -> None:
    """Check that the libraries an estimator of the extra needs are installed.

    Args:
        estimator: the estimator's name, for the message.
        ppf: it needs OpenCV's ``ppf_match_3d``.
        open3d: it needs Open3D.

    Raises:
        AssetError: one is missing, in one line saying how to install the extra.
    """
    missing = [
        lib
        for lib, wanted, there in (
            ("OpenCV's contrib module ppf_match_3d", ppf, has_ppf),
            ("Open3D", open3d, has_open3d),
        )
        if wanted and not there()
    ]
    if missing:
        raise AssetError(
            f"estimator {estimator!r} needs {' and '.join(missing)}, of the optional extra "
            f"'peers': {INSTALL_HINT}"
        )
