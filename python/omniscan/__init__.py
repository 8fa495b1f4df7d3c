"""omniscan: 360° Gaussian-splat digital twins from bimanual in-hand scans.

Every stage of the Omni-Scan pipeline is a function here, over paths on
disk, with the library's settings as keyword arguments (the same names and
defaults as the command line's flags, underscores for dashes) and a report
back::

    import omniscan
    omniscan.simulate(object="builtin:remote", out="scan", width=160, height=120)
    omniscan.mask("scan")
    report = omniscan.twin("scan", out="twin", steps=2000)
    print(report.stages.twin.report.splats, report.to_dict())

Long work runs without the GIL; ``progress=`` takes an object with any of
``start(label, total, unit)``, ``set(done)``, ``advance()``,
``message(text)``, ``finish()``, ``note(line)`` (``omniscan.progress.Tqdm``
draws bars with tqdm). Errors raise :class:`OmniscanError` subclasses whose
message names the file and the problem, as the command line's do.
"""

from __future__ import annotations

import json
import os
from typing import Any, Iterable, Mapping, Optional, Sequence, Union

# Mesa's device-select layer looks for a Wayland display when wgpu lists
# GPUs, and prints an error where there is no session (servers, CI); the
# command line turns it off the same way (crates/omniscan/src/main.rs).
if not any(os.environ.get(k) for k in ("XDG_RUNTIME_DIR", "MESA_VK_DEVICE_SELECT", "NODEVICE_SELECT")):
    os.environ["NODEVICE_SELECT"] = "1"

from . import _omniscan  # noqa: E402
from .errors import FileError, InputError, OmniscanError, OutputInUse
from .models import PointCloud, Splats, read_cloud, read_splats, write_cloud, write_splats
from .report import Report

__all__ = [
    "simulate",
    "mask",
    "train",
    "align",
    "twin",
    "evaluate",
    "render",
    "inspect",
    "make_copy",
    "convert",
    "view",
    "mesh",
    "asset",
    "import_ros2",
    "read_splats",
    "write_splats",
    "read_cloud",
    "write_cloud",
    "settings",
    "allow_outside_paths",
    "use_gpu",
    "Splats",
    "PointCloud",
    "Report",
    "OmniscanError",
    "InputError",
    "FileError",
    "OutputInUse",
    "__version__",
]

__version__: str = _omniscan.__version__

PathLike = Union[str, "os.PathLike[str]"]


def settings(stage: str) -> dict:
    """The default settings of ``stage`` ("train", "twin", ...): the keyword
    arguments its function takes, with their defaults."""
    return {k: _shortest(v) for k, v in json.loads(_omniscan.default_settings(stage)).items()}


def _shortest(value: Any) -> Any:
    """A single-precision default (0.15 arrives as 0.15000000596046448) as
    the number it was written as."""
    if isinstance(value, float):
        import numpy as np

        single = np.float32(value)
        if float(single) == value:
            return float(str(single))
    return value


def allow_outside_paths(allow: bool = True) -> None:
    """Lets captures and photo sets name files outside their folder, for
    this process (the command line's ``--allow-outside-paths``)."""
    _omniscan.allow_outside_paths(bool(allow))


def use_gpu(gpu: Optional[Union[int, str]] = None) -> None:
    """Makes every GPU this process opens the one ``gpu`` names: an index
    among the hardware adapters or a PCI bus id ("0000:3b:00.0"); None
    restores wgpu's high-performance adapter (the command line's ``--gpu``)."""
    _omniscan.use_gpu(None if gpu is None else str(gpu))


def _settings_json(stage: str, kwargs: Mapping[str, Any]) -> str:
    allowed = settings(stage)
    if stage == "mask":
        allowed["evaluate"] = False
    unknown = sorted(set(kwargs) - set(allowed))
    if unknown:
        raise TypeError(
            f"{stage}() got unexpected keyword arguments {unknown}; "
            f"it takes {sorted(allowed)}"
        )
    return json.dumps({k: _plain(v) for k, v in kwargs.items()})


def _plain(value: Any) -> Any:
    """Paths as strings, tuples as lists: what the settings' JSON holds."""
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _run(stage: str, paths: Sequence[Any], kwargs: dict, progress: Any) -> Report:
    text = _omniscan.run_stage(
        stage,
        [os.fspath(p) for p in paths],
        _settings_json(stage, kwargs),
        progress,
    )
    return Report(json.loads(text), kind=stage)


def simulate(*, out: PathLike, progress: Any = None, **settings: Any) -> Report:
    """Simulates a bimanual in-hand scan of ``object`` into the capture folder
    ``out`` (images, depth, ground truth). Keyword arguments: the simulator's
    settings (``object``, ``width``, ``height``, ``seed``, ``slip_deg``,
    ``slip_mm``, ``defect``, ``wrist_angles``, ``latitudes``, ...)."""
    return _run("simulate", [out], settings, progress)


def mask(
    capture: PathLike, *, evaluate: bool = False, progress: Any = None, **settings: Any
) -> Report:
    """Writes the capture's gripper and object masks (paper, "Object masks")
    and records them in its capture.json; with ``evaluate=True`` scores them
    against a simulated capture's ground truth (IoU per arm)."""
    report = _run("mask", [capture], {**settings, "evaluate": evaluate}, progress)
    return report


def train(capture: PathLike, *, out: PathLike, progress: Any = None, **settings: Any) -> Report:
    """Trains a splat model of one arm's views (``arm="left"``, "right") or
    both merged (``arm="both"``) into ``out`` (a 3DGS PLY)."""
    return _run("train", [capture, out], settings, progress)


def align(
    source: PathLike,
    target: PathLike,
    *,
    out: PathLike,
    progress: Any = None,
    **settings: Any,
) -> Report:
    """Registers ``source`` (a splat model or point cloud: the right arm's)
    onto ``target`` (the left arm's) and writes the transform, a JSON 4x4
    matrix, to ``out``. Keyword arguments: the method (``method="auto"`` is
    the paper's rule), the capture whose handover starts it, ..."""
    return _run("align", [source, target, out], settings, progress)


def twin(capture: PathLike, *, out: PathLike, progress: Any = None, **settings: Any) -> Report:
    """The whole twin into the folder ``out``: both arms' models, their
    alignment, the merged model; resumable, and reusing finished stages."""
    return _run("twin", [capture, out], settings, progress)


def evaluate(model: PathLike, capture: PathLike, *, progress: Any = None, **settings: Any) -> Report:
    """PSNR and SSIM (and LPIPS with a network) of ``model`` against the
    capture's or photo set's views."""
    return _run("evaluate", [model, capture], settings, progress)


def render(model: PathLike, *, out: PathLike, progress: Any = None, **settings: Any) -> Report:
    """Renders ``model`` into PNG images in the folder ``out``: a turntable,
    or a capture's cameras (``capture=``)."""
    return _run("render", [model, out], settings, progress)


def inspect(
    models: Iterable[PathLike], *, out: PathLike, progress: Any = None, **settings: Any
) -> Report:
    """Finds the defective copy among three or more models of a part and
    writes verdict.json, renders and report.html into ``out``."""
    return _run("inspect", [out, *models], settings, progress)


def make_copy(model: PathLike, *, out: PathLike, progress: Any = None, **settings: Any) -> Report:
    """Writes a copy of ``model`` as another scan of the part would give it,
    with a planted defect when ``defect=`` names one."""
    return _run("make_copy", [model, out], settings, progress)


def convert(model: PathLike, *, out: PathLike, progress: Any = None, **settings: Any) -> Report:
    """Writes ``model`` to ``out`` in the format its extension names: .ply,
    .spz, .glb or .splat (.compressed.ply is read too)."""
    return _run("convert", [model, out], settings, progress)


def view(models: Iterable[PathLike], *, out: PathLike, progress: Any = None, **settings: Any) -> Report:
    """Writes ``out``, one HTML file that shows ``models`` in 3D in any
    browser, offline."""
    return _run("view", [out, *models], settings, progress)


def mesh(model: PathLike, *, out: PathLike, progress: Any = None, **settings: Any) -> Report:
    """Writes a watertight, coloured triangle mesh of the twin ``model``
    (metres) into the folder ``out``: OBJ + MTL + PNG, PLY, GLB, mesh.json."""
    return _run("mesh", [model, out], settings, progress)


def asset(model: PathLike, *, out: PathLike, progress: Any = None, **settings: Any) -> Report:
    """Writes a simulation asset of the twin ``model`` into the folder
    ``out``: the mesh, convex collision pieces, mass and inertia, as URDF
    and MuJoCo MJCF."""
    return _run("asset", [model, out], settings, progress)


def import_ros2(bag: PathLike, *, out: PathLike, progress: Any = None, **settings: Any) -> Report:
    """Makes the capture folder ``out`` (which must not exist) from the ROS 2
    bag ``bag`` (MCAP or sqlite3, a file or its folder): images, depth and
    camera_info, gripper poses from TF, phases from /omniscan/phase
    (docs/ros2.md)."""
    return _run("import_ros2", [bag, out], settings, progress)
