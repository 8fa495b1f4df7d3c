use omniscan_core::capture::Capture;
use omniscan_core::image_io;
use omniscan_mask::object::{ObjectInputs, object_mask};
use omniscan_mask::pipeline::Masker;
use omniscan_mask::plane::Plane;
use omniscan_mask::segment::CandidateProposer;
use omniscan_mask::MaskSettings;
use nalgebra::Point3;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let capture = Capture::load(std::path::Path::new(&args[1])).unwrap();
    let index: usize = capture.file.frames.iter().position(|f| f.file_path.contains(&args[2])).unwrap();
    let masker = Masker::new(&capture, None, MaskSettings::default()).unwrap();
    let frame = &capture.file.frames[index];
    let image = image_io::read_rgb(&capture.resolve(&frame.file_path)).unwrap();
    let depth = Plane::depth_metres(&image_io::read_depth(&capture.resolve(frame.depth_path.as_ref().unwrap())).unwrap());
    let empty = capture.file.empty_frames.iter().find(|e| e.arm == frame.arm && e.trajectory.unwrap().wrist_index == frame.trajectory.unwrap().wrist_index && e.trajectory.unwrap().latitude_index == frame.trajectory.unwrap().latitude_index).unwrap();
    let empty_depth = Plane::depth_metres(&image_io::read_depth(&capture.resolve(empty.depth_path.as_ref().unwrap())).unwrap());
    let gripper = masker.gripper.mask(&frame.gripper_to_world.0, frame.gripper_opening_m.unwrap(), &image, &depth);
    let next = image_io::read_rgb(&capture.resolve(&capture.file.frames[index + 1].file_path)).unwrap();
    let moving = masker.flow.flow(&image, &next).unwrap().moving(0.5);
    let tool = capture.camera_to_world().inverse() * (frame.gripper_to_world.0 * Point3::origin());
    let inputs = ObjectInputs { image: &image, depth_m: &depth, empty_depth_m: &empty_depth, gripper: &gripper, empty_gripper: Some(&masker.gripper.project(&empty.gripper_to_world.0, 0.0).mask), moving: &moving, tool_depth_m: tool.z as f32 };
    println!("tool depth {:.3}", tool.z);
    let out = object_mask(&inputs, masker.proposer.as_ref(), &masker.settings.object).unwrap();
    let limit = tool.z as f32 + masker.settings.object.near_margin_m;
    let near = Plane { width: depth.width, height: depth.height, data: depth.data.iter().map(|&d| d > 0.0 && d < limit).collect() };
    let seg = masker.proposer.propose(&image, &depth, &near, &gripper).unwrap();
    for (l, c) in out.candidates.iter().enumerate() {
        if c.pixels < 100 { continue; }
        let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
        for (i, &s) in seg.labels.data.iter().enumerate() { if s == l as u32 { let (x, y) = (i % depth.width, i / depth.width); x0 = x0.min(x); y0 = y0.min(y); x1 = x1.max(x); y1 = y1.max(y); } }
        println!("{l}: {:?} bbox ({x0},{y0})-({x1},{y1})", c);
    }
    // Save moving and near masks.
    image_io::write_mask(std::path::Path::new("/work/tmp/moving.png"), &moving.to_mask()).unwrap();
    image_io::write_mask(std::path::Path::new("/work/tmp/near.png"), &near.to_mask()).unwrap();
}
