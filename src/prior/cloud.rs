//! The nodes a field is evaluated at, laid out for the CPU kernel, and where their fields are
//! evaluated.

use std::sync::Arc;

use super::gpu::GpuPrior;

/// Nodes per block: 64 × 6 f32 arrays stay in L1 and fill whole AVX-512 registers.
pub const BLOCK: usize = 64;

/// Positions of the nodes a field is evaluated at: f32, structure of arrays, in whole blocks (the
/// last one padded with zeros, whose results are never written out).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct NodeCloud {
    len: usize,
    pub(super) x: Vec<[f32; BLOCK]>,
    pub(super) y: Vec<[f32; BLOCK]>,
    pub(super) z: Vec<[f32; BLOCK]>,
    /// Set when the cloud is also uploaded to the GPU and fields over it are evaluated there.
    resident: Option<Resident>,
}

/// Where a node cloud lives on the GPU: the device and the cloud's index there.
#[derive(Clone, Debug)]
pub struct Resident {
    pub gpu: Arc<GpuPrior>,
    pub cloud: usize,
}

impl PartialEq for Resident {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.gpu, &other.gpu) && self.cloud == other.cloud
    }
}

impl NodeCloud {
    pub fn new(positions: impl ExactSizeIterator<Item = [f64; 3]>) -> Self {
        let len = positions.len();
        let blocks = len.div_ceil(BLOCK);
        let mut cloud = NodeCloud {
            len,
            x: vec![[0.0; BLOCK]; blocks],
            y: vec![[0.0; BLOCK]; blocks],
            z: vec![[0.0; BLOCK]; blocks],
            resident: None,
        };
        for (i, p) in positions.enumerate() {
            let (b, o) = (i / BLOCK, i % BLOCK);
            cloud.x[b][o] = p[0] as f32;
            cloud.y[b][o] = p[1] as f32;
            cloud.z[b][o] = p[2] as f32;
        }
        cloud
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The position of node `i`, as the kernels see it (f32).
    pub fn position(&self, i: usize) -> [f32; 3] {
        let (b, o) = (i / BLOCK, i % BLOCK);
        [self.x[b][o], self.y[b][o], self.z[b][o]]
    }

    /// Every node's position, in order.
    pub fn positions(&self) -> impl ExactSizeIterator<Item = [f32; 3]> + '_ {
        (0..self.len).map(|i| self.position(i))
    }

    /// Evaluates fields over this cloud on the GPU from now on (the cloud must be uploaded there).
    pub fn make_resident(&mut self, resident: Resident) {
        self.resident = Some(resident);
    }

    /// Where fields over this cloud are evaluated, if on a GPU.
    pub fn resident(&self) -> Option<&Resident> {
        self.resident.as_ref()
    }
}
