//! Grid update constants: `v_i = mv_i/m_i + dt g` for nodes with `m_i > 1e-8 dx³` (kg), then
//! the boundary conditions; nodes below the mass threshold get `v = 0` (the kernels are in
//! `crate::wide`).

/// Mass threshold `1e-8 dx³` (kg) below which a node is considered empty (PAC-NeRF).
#[inline]
pub fn mass_threshold(dx: f64) -> f64 {
    1e-8 * dx * dx * dx
}
