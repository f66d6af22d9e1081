//! `nak mesh info`: what a biomechanics engineer checks before trusting a mesh.

use std::io::Write;

use nak::mesh::TetMesh;

pub fn print(out: &mut impl Write, mesh: &TetMesh) -> std::io::Result<()> {
    let (lo, hi) = mesh.bounding_box();
    let q = mesh.quality();
    let litres = |v: f64| v * 1e6;
    writeln!(out, "mesh        {}", mesh.origin)?;
    writeln!(out, "name        {}", mesh.config.name)?;
    writeln!(out, "hash        {}", mesh.content_hash)?;
    writeln!(
        out,
        "nodes       {} ({} on the surface)",
        mesh.node_count(),
        mesh.surface_nodes.len()
    )?;
    writeln!(out, "tetrahedra  {}", mesh.tets.len())?;
    writeln!(out, "surface     {} triangles, closed and manifold", mesh.surface.len())?;
    writeln!(
        out,
        "bounds      x [{:.1}, {:.1}]  y [{:.1}, {:.1}]  z [{:.1}, {:.1}] mm  (size {:.0} × {:.0} × {:.0} mm)",
        lo[0] * 1e3,
        hi[0] * 1e3,
        lo[1] * 1e3,
        hi[1] * 1e3,
        lo[2] * 1e3,
        hi[2] * 1e3,
        (hi[0] - lo[0]) * 1e3,
        (hi[1] - lo[1]) * 1e3,
        (hi[2] - lo[2]) * 1e3
    )?;
    writeln!(out, "volume      {:.1} mL", litres(mesh.total_volume()))?;
    writeln!(out, "regions")?;
    for (i, r) in mesh.regions.iter().enumerate() {
        let count = mesh.tet_region.iter().filter(|&&t| t as usize == i).count();
        let m = &mesh.config.materials[&r.name];
        writeln!(
            out,
            "  {:<14} {:>8.1} mL  {:>7} tets  μ = {:.2} kPa  ν = {:.2}  C10 = {:.3} kPa  C01 = {:.3} kPa",
            r.name,
            litres(r.volume),
            count,
            m.shear_modulus / 1e3,
            m.poisson_ratio,
            m.c10 / 1e3,
            m.c01 / 1e3
        )?;
    }
    writeln!(out, "node sets")?;
    for (name, nodes) in &mesh.node_sets {
        writeln!(out, "  {:<14} {:>6} nodes", name, nodes.len())?;
    }
    writeln!(
        out,
        "quality     dihedral angles [{:.1}°, {:.1}°]; aspect ratio (1 = regular) max {:.2}, mean {:.2}",
        q.min_dihedral_deg, q.max_dihedral_deg, q.max_aspect, q.mean_aspect
    )?;
    let p = mesh.config.prior;
    writeln!(
        out,
        "prior       Kelvinlet ν = {}, ε = {} m, λ = {}",
        p.poisson_ratio, p.epsilon, p.lambda
    )?;
    Ok(())
}
