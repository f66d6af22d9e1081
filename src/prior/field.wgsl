// The multi-point regularized Kelvinlet field (docs/design.md §3), one invocation per node:
// u(x) = Σ_j [(a/r_ε + b/r_ε³) k_j + r (r·k_j)/r_ε³],  r = x − x_j,  r_ε = sqrt(|r|² + ε²),
// with the scale s folded into the coefficients k_j (as in the CPU kernel, kernel.rs).
// A request may add a resident basis's field Φ g (a reduced network's residual, docs/design.md §7) in the
// same pass: Φ for the request's cloud stored mode by mode, [M, 3, N], so that neighbouring
// invocations read neighbouring words; g in `points` after its interaction points.
// One dispatch serves a batch of requests: workgroup row y is request y.

struct Job {
    // Offset and length of the request's node cloud in `positions`.
    cloud_offset: u32,
    cloud_len: u32,
    // Offset and count of its interaction points in `points` (two vec4 per point).
    point_offset: u32,
    point_count: u32,
    // Where its (N, 3) rows start in `field`.
    out_offset: u32,
    a: f32,
    b: f32,
    epsilon_sq: f32,
    // Modes of the basis to add (0: none), where the cloud's rows start in `basis` (floats), and
    // where g starts in `points` (vec4s).
    modes: u32,
    basis_offset: u32,
    coefficient_offset: u32,
}

@group(0) @binding(0) var<storage, read> positions: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> jobs: array<Job>;
@group(0) @binding(3) var<storage, read_write> field: array<f32>;
@group(0) @binding(4) var<storage, read> basis: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let job = jobs[id.y];
    let i = id.x;
    if (i >= job.cloud_len) {
        return;
    }
    let x = positions[job.cloud_offset + i].xyz;
    var u = vec3<f32>(0.0, 0.0, 0.0);
    for (var j = 0u; j < job.point_count; j++) {
        let p = points[2u * (job.point_offset + j)].xyz;
        let k = points[2u * (job.point_offset + j) + 1u].xyz;
        let r = x - p;
        let inv = 1.0 / sqrt(dot(r, r) + job.epsilon_sq);
        let inv3 = inv * inv * inv;
        u += (job.a * inv + job.b * inv3) * k + (dot(r, k) * inv3) * r;
    }
    let n = job.cloud_len;
    for (var m = 0u; m < job.modes; m++) {
        let g = points[job.coefficient_offset + m / 4u][m % 4u];
        let at = job.basis_offset + 3u * m * n + i;
        u += g * vec3<f32>(basis[at], basis[at + n], basis[at + 2u * n]);
    }
    let o = job.out_offset + 3u * i;
    field[o] = u.x;
    field[o + 1u] = u.y;
    field[o + 2u] = u.z;
}
