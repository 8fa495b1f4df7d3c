//! The `omniscan` binary: the command line of the `omniscan` library crate.

/// mimalloc instead of the system allocator: a training step frees and
/// takes back hundreds of megabytes of image-sized buffers (SSIM's blurs,
/// per-pixel gradients), which glibc hands to the kernel and maps again each
/// time; the page clearing and TLB shootdowns of that doubled SSIM's time on
/// the 2-core development VM (docs/results.md).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() {
    quiet_headless_gpu_probe();
    std::process::exit(omniscan::run_from(std::env::args_os()));
}

/// Mesa's Vulkan device-select layer looks for the GPU driving a Wayland
/// display when the instance lists its devices; on a machine without a
/// session (no `XDG_RUNTIME_DIR`: servers, CI, containers) libwayland then
/// prints "error: XDG_RUNTIME_DIR is invalid or not set" twice, although
/// nothing is wrong and the GPU, if any, is used. There the layer has no
/// display to find, so it is turned off (`NODEVICE_SELECT`), unless the user
/// picked a device through it (`MESA_VK_DEVICE_SELECT`). Set before any
/// thread starts, as the environment must be.
fn quiet_headless_gpu_probe() {
    let unset = |key: &str| std::env::var_os(key).is_none();
    if unset("XDG_RUNTIME_DIR") && unset("MESA_VK_DEVICE_SELECT") && unset("NODEVICE_SELECT") {
        // SAFETY: called first thing in `main`, while this is the only thread.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
}
