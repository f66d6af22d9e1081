//! Fill-reducing ordering for the elasticity tangent: METIS's nested dissection of the mesh's node
//! graph, each node's DOFs kept together.
//!
//! On a 3D tetrahedral mesh nested dissection leaves far less fill in the Cholesky factor than
//! approximate minimum degree (faer's built-in ordering); ordering nodes rather than scalar DOFs
//! keeps each node's three DOFs in one supernode column block.

use super::FemError;

/// Nested dissection of the nodes for which `has_unknowns` holds, adjacent when they share a
/// tetrahedron: those nodes in elimination order.
pub fn nested_dissection(
    tets: &[[u32; 4]],
    nodes: usize,
    has_unknowns: impl Fn(u32) -> bool,
) -> Result<Vec<u32>, FemError> {
    let mut vertex = vec![u32::MAX; nodes];
    let mut vertices = Vec::new();
    for n in 0..nodes as u32 {
        if has_unknowns(n) {
            vertex[n as usize] = vertices.len() as u32;
            vertices.push(n);
        }
    }
    let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); vertices.len()];
    for tet in tets {
        for &a in tet {
            for &b in tet {
                let (va, vb) = (vertex[a as usize], vertex[b as usize]);
                if a != b && va != u32::MAX && vb != u32::MAX {
                    neighbours[va as usize].push(vb);
                }
            }
        }
    }
    let mut xadj = Vec::with_capacity(vertices.len() + 1);
    let mut adjncy = Vec::new();
    xadj.push(0);
    for list in &mut neighbours {
        list.sort_unstable();
        list.dedup();
        adjncy.extend(list.iter().map(|&v| v as metis_sys::idx_t));
        xadj.push(adjncy.len() as metis_sys::idx_t);
    }
    let order = metis_node_nd(&mut xadj, &mut adjncy)?;
    Ok(order.into_iter().map(|v| vertices[v]).collect())
}

/// METIS_NodeND on a graph in CSR form; returns the vertices in elimination order.
fn metis_node_nd(xadj: &mut [metis_sys::idx_t], adjncy: &mut [metis_sys::idx_t]) -> Result<Vec<usize>, FemError> {
    let mut n = (xadj.len() - 1) as metis_sys::idx_t;
    let mut options = [0 as metis_sys::idx_t; metis_sys::METIS_NOPTIONS as usize];
    let mut perm = vec![0 as metis_sys::idx_t; n as usize];
    let mut iperm = vec![0 as metis_sys::idx_t; n as usize];
    // SAFETY: the arrays outlive the call and have the lengths METIS reads and writes: xadj n + 1,
    // adjncy xadj[n], options METIS_NOPTIONS, perm and iperm n; a null vertex weight means unit weights.
    let status = unsafe {
        metis_sys::METIS_SetDefaultOptions(options.as_mut_ptr());
        metis_sys::METIS_NodeND(
            &mut n,
            xadj.as_mut_ptr(),
            adjncy.as_mut_ptr(),
            std::ptr::null_mut(),
            options.as_mut_ptr(),
            perm.as_mut_ptr(),
            iperm.as_mut_ptr(),
        )
    };
    if status != metis_sys::rstatus_et_METIS_OK {
        return Err(FemError::Assembly(format!(
            "METIS nested dissection failed (status {status})"
        )));
    }
    // METIS: row i of the permuted matrix is row perm[i] of the original.
    Ok(perm.into_iter().map(|v| v as usize).collect())
}
