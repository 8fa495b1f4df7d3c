//! Which GPU a process opens. wgpu's high-performance preference takes the
//! same device in every process, which on a node with several GPUs puts
//! every task on one of them: a scheduler (Ray, Slurm) assigns each task a
//! GPU, and `--gpu INDEX|PCI_BUS_ID` tells omniscan which. An index counts
//! the hardware adapters in wgpu's order (Vulkan, Metal or DX12; not GL,
//! which lists the same devices again); a PCI bus id (`0000:3b:00.0`, as
//! `nvidia-smi --query-gpu=pci.bus_id` prints it) names one device
//! whatever the order.

use std::sync::RwLock;

use crate::SplatError;

/// The GPU to open.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum GpuSelector {
    /// wgpu's high-performance adapter.
    #[default]
    Preferred,
    /// The n-th hardware adapter, from 0.
    Index(usize),
    /// The adapter on this PCI bus.
    PciBusId(String),
}

impl std::str::FromStr for GpuSelector {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim();
        if s.is_empty() {
            return Err("--gpu takes an index (0, 1, ...) or a PCI bus id (0000:3b:00.0)".into());
        }
        Ok(match s.parse::<usize>() {
            Ok(index) => GpuSelector::Index(index),
            Err(_) => GpuSelector::PciBusId(s.to_ascii_lowercase()),
        })
    }
}

static SELECTED: RwLock<GpuSelector> = RwLock::new(GpuSelector::Preferred);

/// Every GPU this process opens from now on is `selector`'s (the CLI's
/// global `--gpu`; Python's `omniscan.use_gpu`).
pub fn select_gpu(selector: GpuSelector) {
    *SELECTED.write().unwrap_or_else(|e| e.into_inner()) = selector;
}

pub(crate) fn selected() -> GpuSelector {
    SELECTED.read().unwrap_or_else(|e| e.into_inner()).clone()
}

/// Whether two PCI bus ids name one bus: drivers write the domain or
/// leave it out (`0000:3b:00.0`, `3b:00.0`).
fn same_bus(a: &str, b: &str) -> bool {
    let strip = |s: &str| {
        let s = s.to_ascii_lowercase();
        match s.matches(':').count() {
            2 => s.split_once(':').map(|x| x.1.to_string()).unwrap_or(s),
            _ => s,
        }
    };
    !a.is_empty() && strip(a) == strip(b)
}

/// The adapter `selector` names among `adapters` (with their info), or
/// an error listing the ones there are.
pub(crate) fn pick(
    selector: &GpuSelector,
    adapters: Vec<(wgpu::Adapter, wgpu::AdapterInfo)>,
) -> Result<wgpu::Adapter, SplatError> {
    let hardware: Vec<(wgpu::Adapter, wgpu::AdapterInfo)> = adapters
        .into_iter()
        .filter(|(_, info)| info.backend != wgpu::Backend::Gl)
        .collect();
    let listed = || {
        hardware
            .iter()
            .enumerate()
            .map(|(i, (_, info))| {
                format!(
                    "{i}: {} ({:?}, bus {})",
                    info.name, info.device_type, info.device_pci_bus_id
                )
            })
            .collect::<Vec<_>>()
            .join("; ")
    };
    let found = match selector {
        GpuSelector::Preferred => unreachable!("the preferred adapter is requested, not picked"),
        GpuSelector::Index(i) => hardware.get(*i).map(|(a, _)| a.clone()),
        GpuSelector::PciBusId(id) => hardware
            .iter()
            .find(|(_, info)| same_bus(&info.device_pci_bus_id, id))
            .map(|(a, _)| a.clone()),
    };
    found.ok_or_else(|| {
        SplatError::Invalid(format!(
            "GPU backend: --gpu {} names no adapter; there are: {}",
            match selector {
                GpuSelector::Index(i) => i.to_string(),
                GpuSelector::PciBusId(id) => id.clone(),
                GpuSelector::Preferred => String::new(),
            },
            match listed() {
                l if l.is_empty() => "none".to_string(),
                l => l,
            }
        ))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn selectors_parse_and_bus_ids_match_with_or_without_domain() {
        assert_eq!("1".parse::<GpuSelector>().unwrap(), GpuSelector::Index(1));
        assert_eq!(
            "0000:3B:00.0".parse::<GpuSelector>().unwrap(),
            GpuSelector::PciBusId("0000:3b:00.0".into())
        );
        assert!("".parse::<GpuSelector>().is_err());
        assert!(same_bus("0000:3b:00.0", "3b:00.0"));
        assert!(same_bus("3B:00.0", "0000:3b:00.0"));
        assert!(!same_bus("0000:3b:00.0", "0000:3c:00.0"));
        assert!(!same_bus("", "0000:3b:00.0"));
    }
}
