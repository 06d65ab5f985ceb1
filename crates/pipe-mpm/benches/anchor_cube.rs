//! The anchors' MPM workload cube (`../shared/anchors/README.md`), shared by the `mpm` bench
//! and the root package's `simulate_anchor` bench (included with `#[path]`).

use glam::DVec3;

/// `n` particle positions (m) uniform in a cube of side `min((n/8)^(1/3)·dx, 1 − 10·dx)`,
/// dx = 1/g, with its lower corner at `(0.5 − side/2, 0.5 − side/2 + 0.1·(1 − side),
/// 0.5 − side/2)` (8 particles per cell, placed as the anchors place it), in random order
/// from a fixed xorshift stream; and the particle volume `side³/n` (m³, dx³/8 unless the cube
/// was clamped).
pub fn anchor_cube(n: usize, g: usize) -> (Vec<DVec3>, f64) {
    let dx = 1.0 / g as f64;
    let side = ((n as f64 / 8.0).cbrt() * dx).min(1.0 - 10.0 * dx);
    let mut seed = 0x2545F4914F6CDD1Du64;
    let mut r = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let lo = DVec3::new(
        0.5 - side / 2.0,
        0.5 - side / 2.0 + 0.1 * (1.0 - side),
        0.5 - side / 2.0,
    );
    let x = (0..n)
        .map(|_| lo + DVec3::new(r(), r(), r()) * side)
        .collect();
    (x, side * side * side / n as f64)
}
