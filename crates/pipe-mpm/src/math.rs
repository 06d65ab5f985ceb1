//! Small f64 matrix helpers on top of `glam` (column-major `DMat3`).

use glam::{DMat3, DVec3};

/// Element `(row, col)` of a column-major matrix.
#[inline]
pub fn el(m: &DMat3, row: usize, col: usize) -> f64 {
    m.col(col)[row]
}

/// Matrix from row-major rows `m[row][col]`.
#[inline]
pub fn from_rows(rows: [[f64; 3]; 3]) -> DMat3 {
    DMat3::from_cols_array_2d(&rows).transpose()
}

/// Row-major rows of a matrix.
#[inline]
pub fn to_rows(m: &DMat3) -> [[f64; 3]; 3] {
    m.transpose().to_cols_array_2d()
}

/// Outer product `a bᵀ`.
#[inline]
pub fn outer(a: DVec3, b: DVec3) -> DMat3 {
    DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

/// Frobenius inner product `A : B = Σ A_ij B_ij`.
#[inline]
pub fn ddot(a: &DMat3, b: &DMat3) -> f64 {
    a.x_axis.dot(b.x_axis) + a.y_axis.dot(b.y_axis) + a.z_axis.dot(b.z_axis)
}

/// Trace.
#[inline]
pub fn trace(m: &DMat3) -> f64 {
    m.x_axis.x + m.y_axis.y + m.z_axis.z
}

/// Diagonal of a matrix.
#[inline]
pub fn diagonal(m: &DMat3) -> DVec3 {
    DVec3::new(m.x_axis.x, m.y_axis.y, m.z_axis.z)
}

/// `true` when every entry is finite.
#[inline]
pub fn mat_finite(m: &DMat3) -> bool {
    m.is_finite()
}

/// Cofactor matrix `d det(F) / dF = det(F) F⁻ᵀ`, defined for singular F too.
#[inline]
pub fn cofactor(f: &DMat3) -> DMat3 {
    let (c0, c1, c2) = (f.x_axis, f.y_axis, f.z_axis);
    // For columns c0,c1,c2: det = c0 · (c1 × c2); d det / d c0 = c1 × c2, etc.
    DMat3::from_cols(c1.cross(c2), c2.cross(c0), c0.cross(c1))
}

/// Largest absolute entry; NaN when an entry is NaN (which `f64::max` alone would drop, so a
/// NaN never passes a tolerance check).
#[inline]
pub fn max_abs(m: &DMat3) -> f64 {
    if m.is_nan() {
        return f64::NAN;
    }
    m.x_axis
        .abs()
        .max_element()
        .max(m.y_axis.abs().max_element())
        .max(m.z_axis.abs().max_element())
}
