"""Type stubs of the omniscan package (written by scripts/python-stubs)."""

import os
from typing import Any, Iterable, Optional, Sequence, Union

from .errors import FileError as FileError, InputError as InputError, OmniscanError as OmniscanError, OutputInUse as OutputInUse
from .models import PointCloud as PointCloud, Splats as Splats
from .models import read_cloud as read_cloud, read_splats as read_splats, write_cloud as write_cloud, write_splats as write_splats
from .report import Report as Report

PathLike = Union[str, os.PathLike[str]]
__version__: str

def settings(stage: str) -> dict: ...
def allow_outside_paths(allow: bool = True) -> None: ...
def use_gpu(gpu: Optional[Union[int, str]] = None) -> None: ...

def simulate(*, out: PathLike, camera_distance_m: Optional[Any] = None, defect: Optional[Any] = None, depth_noise_mm_at_1m: float = 2.0, gripper_dir: Optional[Any] = None, gripper_root: Optional[Any] = None, height: int = 480, latitude_max_deg: float = 70.0, latitude_min_deg: float = -10.0, latitudes: int = 5, no_empty_pass: bool = False, object: str = 'builtin:flashlight', object_scale: Optional[Any] = None, pose_noise_deg: float = 0.0, pose_noise_mm: float = 0.0, robot_mjcf: Optional[Any] = None, robot_urdf: Optional[Any] = None, seed: int = 0, slip_deg: float = 0.0, slip_mm: float = 0.0, supersample: int = 2, tcp_link: Optional[Any] = None, tcp_offset_m: Optional[Any] = None, width: int = 640, wrist_angles: int = 20, progress: Any = None) -> Report:
    """Simulates a bimanual in-hand scan of ``object`` into the capture folder ..."""

def mask(capture: PathLike, *, evaluate: bool = False, depth_model: Optional[Any] = None, depth_model_output: str = 'disparity', depth_noise_mm_at_1m: float = 2.0, flow_model: Optional[Any] = None, flow_model_input: str = 'bytes', gripper: str = 'kinematic', gripper_dir: Optional[Any] = None, grow_px: int = 0, near_margin_m: float = 0.15, non_gripper_threshold: float = 0.89, non_robot_threshold_mm: float = 8.0, onnx_runtime: Optional[Any] = None, sam_decoder: Optional[Any] = None, sam_encoder: Optional[Any] = None, unet: Optional[Any] = None, progress: Any = None) -> Report:
    """Writes the capture's gripper and object masks (paper, "Object masks") ..."""

def train(capture: PathLike, *, out: PathLike, absgrad: bool = False, antialiased: bool = False, appearance: str = 'auto', arm: str = 'left', backend: str = 'auto', checkpoint_every: int = 500, densification: str = 'adaptive', downscale: int = 2, gpu_view_memory_gb: float = 4.0, grad_threshold: Optional[Any] = None, hold_out_every: int = 8, hold_out_first: Optional[Any] = None, init: Optional[Any] = None, init_right: Optional[Any] = None, initial_points: int = 5000, lpips: Optional[Any] = None, max_splats: int = 200000, no_memory_check: bool = False, onnx_runtime: Optional[Any] = None, pose_arm_rate: float = 0.1, pose_fit_steps: int = 100, pose_from_step: int = 100, pose_regularisation: float = 0.0001, pose_rotation_lr_rad: float = 0.002, pose_translation_lr: float = 0.005, position_lr: float = 0.00016, refine_poses: bool = False, resume: bool = False, right_to_left: Optional[Any] = None, seed: int = 0, sh_degree: int = 3, sh_rest_lr: float = 0.0025, steps: int = 3000, use_ground_truth_masks: bool = False, progress: Any = None) -> Report:
    """Trains a splat model of one arm's views (``arm="left"``, "right") or ..."""

def align(source: PathLike, target: PathLike, *, out: PathLike, downscale: int = 2, handover: Optional[Any] = None, init: Optional[Any] = None, iterations: int = 30, max_distance: Optional[Any] = None, method: str = 'auto', photometric: bool = False, use_ground_truth_masks: bool = False, voxel: Optional[Any] = None, progress: Any = None) -> Report:
    """Registers ``source`` (a splat model or point cloud: the right arm's) ..."""

def twin(capture: PathLike, *, out: PathLike, backend: str = 'auto', checkpoint_every: int = 500, downscale: int = 2, gpu_view_memory_gb: float = 4.0, pose_arm_rate: float = 0.1, pose_fit_steps: int = 100, pose_from_step: int = 100, pose_regularisation: float = 0.0001, pose_rotation_lr_rad: float = 0.002, pose_translation_lr: float = 0.005, refine_poses: bool = False, seed: int = 0, steps: int = 3000, use_ground_truth_masks: bool = False, progress: Any = None) -> Report:
    """The whole twin into the folder ``out``: both arms' models, their ..."""

def evaluate(model: PathLike, capture: PathLike, *, arm: str = 'left', backend: str = 'cpu', downscale: int = 1, fit_poses: bool = False, held_out_every: int = 0, held_out_first: Optional[Any] = None, lpips: Optional[Any] = None, onnx_runtime: Optional[Any] = None, pose_fit_steps: int = 100, renders: Optional[Any] = None, right_to_left: Optional[Any] = None, progress: Any = None) -> Report:
    """PSNR and SSIM (and LPIPS with a network) of ``model`` against the ..."""

def render(model: PathLike, *, out: PathLike, arm: str = 'left', backend: str = 'auto', background: Sequence[Any] = [0.0, 0.0, 0.0], capture: Optional[Any] = None, height: int = 480, orbit: int = 8, right_to_left: Optional[Any] = None, width: int = 640, progress: Any = None) -> Report:
    """Renders ``model`` into PNG images in the folder ``out``: a turntable, ..."""

def inspect(models: Iterable[PathLike], *, out: PathLike, arm: str = 'both', backend: str = 'auto', capture: Optional[Any] = None, close_up: bool = False, colour_threshold: float = 0.3, height: int = 120, no_surface_deviation: bool = False, photometric_radius_mm: float = 15.0, reference: Optional[Any] = None, right_to_left: Optional[Any] = None, seed: int = 0, threshold_mm: float = 4.5, units_per_metre: float = 1.0, views: int = 100, width: int = 160, progress: Any = None) -> Report:
    """Finds the defective copy among three or more models of a part and ..."""

def make_copy(model: PathLike, *, out: PathLike, defect: Optional[Any] = None, keep_pose: bool = False, noise_mm: float = 0.3, seed: int = 0, size_mm: float = 6.0, units_per_metre: float = 1.0, progress: Any = None) -> Report:
    """Writes a copy of ``model`` as another scan of the part would give it, ..."""

def convert(model: PathLike, *, out: PathLike, spz_version: int = 4, progress: Any = None) -> Report:
    """Writes ``model`` to ``out`` in the format its extension names: .ply, ..."""

def view(models: Iterable[PathLike], *, out: PathLike, names: Sequence[Any] = [], title: Optional[Any] = None, progress: Any = None) -> Report:
    """Writes ``out``, one HTML file that shows ``models`` in 3D in any ..."""

def mesh(model: PathLike, *, out: PathLike, faces: int = 20000, inside_vote: float = 0.65, name: Optional[Any] = None, scale_m_per_unit: float = 1.0, texture_px: int = 2048, view_px: int = 320, views: int = 64, voxel_mm: Optional[Any] = None, progress: Any = None) -> Report:
    """Writes a watertight, coloured triangle mesh of the twin ``model`` ..."""

def asset(model: PathLike, *, out: PathLike, decomposition_resolution: int = 64, density_kg_m3: Optional[Any] = None, faces: int = 20000, hulls: int = 16, inside_vote: float = 0.65, mass_kg: Optional[Any] = None, name: Optional[Any] = None, scale_m_per_unit: float = 1.0, texture_px: int = 2048, view_px: int = 320, views: int = 64, voxel_mm: Optional[Any] = None, progress: Any = None) -> Report:
    """Writes a simulation asset of the twin ``model`` into the folder ..."""

def import_ros2(bag: PathLike, *, out: PathLike, camera_drift_mm: float = 1.0, camera_info_topic: str = '/camera/color/camera_info', depth_sync_s: float = 0.01, depth_topic: str = '/camera/depth/image_raw', gripper_root: Optional[Any] = None, image_topic: str = '/camera/color/image_raw', joint_states_topic: str = '/joint_states', left_finger_joint: str = 'gripper_l_joint', left_gripper_frame: str = 'left_gripper', max_tf_gap_s: float = 0.1, opening_m_per_joint_unit: float = 2.0, phase_topic: str = '/omniscan/phase', right_finger_joint: str = 'gripper_r_joint', right_gripper_frame: str = 'right_gripper', robot_mjcf: Optional[Any] = None, robot_urdf: Optional[Any] = None, tcp_link: Optional[Any] = None, tcp_offset_m: Optional[Any] = None, world_frame: str = 'world', progress: Any = None) -> Report:
    """Makes the capture folder ``out`` (which must not exist) from the ROS 2 ..."""
