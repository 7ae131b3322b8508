"""The field's classical depth-based estimators, built in as peers of the learned ones (the
optional extra ``peers``: OpenCV's contrib modules and Open3D).

- ``ppf``: point pair features and OpenCV's ICP (`perception.peers.ppf`);
- ``fpfh-icp``: FPFH features, RANSAC and point-to-plane ICP with Open3D
  (`perception.peers.fpfh`);
- ``ppf-det``, ``fpfh-icp-det``: the same on the points inside the project's detection mask of
  the requested object (`perception.peers.prior`);
- ``hybrid-global-icp``: `hybrid-global`'s pose refined on depth by point-to-plane ICP
  (`perception.peers.icp`).

Each needs the depth image (``--obs-mode rgbd``) and the table's height; without them it answers
no estimate with a note (`perception.peers.estimator`). Importing this package is cheap: each
factory imports its libraries when called, and names the extra when they are missing.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from perception.integrity import recording_loads
from perception.peers.extra import require
from posegrasp.core.contract import PoseEstimator
from posegrasp.core.errors import UnknownNameError


def _ppf(name: str = "ppf", detections: bool = False) -> PoseEstimator:
    require(name, ppf=True)
    from perception.peers.estimator import PeerEstimator
    from perception.peers.ppf import PpfRegistration

    return PeerEstimator(name, PpfRegistration(), prior=_prior() if detections else None)


def _fpfh(name: str = "fpfh-icp", detections: bool = False) -> PoseEstimator:
    require(name, open3d=True)
    from perception.peers.estimator import PeerEstimator
    from perception.peers.fpfh import FpfhRegistration

    return PeerEstimator(name, FpfhRegistration(), prior=_prior() if detections else None)


def _prior():
    from perception.peers.prior import DetectionPrior

    return DetectionPrior()


def _ppf_det() -> PoseEstimator:
    """``ppf`` on the points inside the detection mask."""
    return _ppf("ppf-det", detections=True)


def _fpfh_det() -> PoseEstimator:
    """``fpfh-icp`` on the points inside the detection mask."""
    return _fpfh("fpfh-icp-det", detections=True)


def _hybrid_global_icp() -> PoseEstimator:
    """`hybrid-global`, its pose refined on depth by point-to-plane ICP."""
    require("hybrid-global-icp", open3d=True)
    from perception.global_pose import GlobalPoseEstimator
    from perception.peers.estimator import DepthRefinedEstimator
    from perception.peers.icp import PointToPlaneIcp

    inner = GlobalPoseEstimator.from_weights()
    return DepthRefinedEstimator("hybrid-global-icp", inner, PointToPlaneIcp())


#: The peers' factories by name; every one of them needs the depth image.
PEER_ESTIMATORS: dict[str, Callable[[], PoseEstimator]] = {
    "ppf": _ppf,
    "ppf-det": _ppf_det,
    "fpfh-icp": _fpfh,
    "fpfh-icp-det": _fpfh_det,
    "hybrid-global-icp": _hybrid_global_icp,
}


def peer_weights_files(name: str) -> tuple[Path, ...]:
    """The weights files the peer `name` loads (resolved, in load order): the detector's for
    ``-det``, `hybrid-global`'s for ``hybrid-global-icp``, none for ``ppf`` and ``fpfh-icp``.
    Makes the estimator to find out.

    Raises:
        UnknownNameError: `name` is not in `PEER_ESTIMATORS`, listing those that are.
        AssetError: the extra is not installed; missing or corrupt weights.
    """
    if name not in PEER_ESTIMATORS:
        raise UnknownNameError("peer estimator", name, PEER_ESTIMATORS)
    with recording_loads() as files:
        PEER_ESTIMATORS[name]()
    return tuple(files)


__all__ = ["PEER_ESTIMATORS", "peer_weights_files"]
