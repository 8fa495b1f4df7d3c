"""Splat models and point clouds as numpy arrays, read and written by the
library's own readers and writers (so a model read here is the one the
command line reads)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Optional, Union

import numpy as np

from . import _omniscan

PathLike = Union[str, "os.PathLike[str]"]


@dataclass
class Splats:
    """A 3D Gaussian splat model, pre-activation as in the 3DGS PLY.

    ``means`` (N, 3) float32; ``scales`` (N, 3) natural logs of the scales;
    ``quats`` (N, 4) rotations w, x, y, z (not necessarily unit);
    ``opacities`` (N,) logits; ``sh`` (N, K, 3) spherical-harmonics
    coefficients, K = (degree + 1)², basis index major (gsplat's layout).
    """

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray
    antialiased: bool = False
    appearance: str = "view-direction"

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    def __len__(self) -> int:
        return int(self.means.shape[0])


@dataclass
class PointCloud:
    """Points (N, 3) float64, with colours (N, 3) float32 in [0, 1] and
    normals (N, 3) float64 where the file has them."""

    points: np.ndarray
    colors: Optional[np.ndarray] = None
    normals: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return int(self.points.shape[0])


def read_splats(path: PathLike) -> Splats:
    """Reads a splat model: a 3DGS PLY (INRIA / gsplat layout, ASCII or
    binary) or a ``.splat`` web-viewer file, by extension."""
    means, scales, quats, opacities, sh, _degree, antialiased, appearance = (
        _omniscan.read_splats_arrays(os.fspath(path))
    )
    return Splats(means, scales, quats, opacities, sh, antialiased, appearance)


def write_splats(path: PathLike, splats: Splats) -> None:
    """Writes ``splats`` atomically in the format the extension names
    (``.ply``: binary 3DGS PLY; ``.splat``: base colour only); refuses a
    model with mismatched shapes, NaN or infinite values."""
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    _omniscan.write_splats_arrays(
        os.fspath(path),
        f32(splats.means),
        f32(splats.scales),
        f32(splats.quats),
        f32(splats.opacities),
        f32(splats.sh),
        bool(splats.antialiased),
        str(splats.appearance),
    )


def read_cloud(path: PathLike) -> PointCloud:
    """Reads a point cloud: PLY, PCD (ASCII, binary, compressed), XYZ, or
    a splat model's centres."""
    points, colors, normals = _omniscan.read_cloud_arrays(os.fspath(path))
    return PointCloud(points, colors, normals)


def write_cloud(path: PathLike, cloud: PointCloud) -> None:
    """Writes ``cloud`` as a binary PLY, atomically."""
    opt = lambda a, t: None if a is None else np.ascontiguousarray(a, dtype=t)  # noqa: E731
    _omniscan.write_cloud_arrays(
        os.fspath(path),
        np.ascontiguousarray(cloud.points, dtype=np.float64),
        opt(cloud.colors, np.float32),
        opt(cloud.normals, np.float64),
    )
