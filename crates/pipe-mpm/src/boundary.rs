//! Grid boundary conditions: ground plane / half-spaces, boxes, and the domain walls.
//!
//! Each acts on grid node velocities after the grid update. With `n` the unit normal pointing
//! out of the obstacle (into the free region):
//! sticky `v = 0`; slip `v ← v − (v·n) n` (tangential part kept); separating: slip only when
//! `v·n < 0` (the node moves into the obstacle), free otherwise.

use glam::DVec3;

use crate::error::MpmError;
use crate::grid::{Aabb, GridSpec};

/// How a boundary treats node velocities.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BoundaryKind {
    /// `v = 0`.
    Sticky,
    /// Remove the normal component.
    Slip,
    /// Remove the normal component only when it points into the obstacle.
    Separate,
}

/// Tolerance (m) of the half-space test `(x − p)·n ≤ 1e-6` (PAC-NeRF's ground rule).
pub const PLANE_EPS: f64 = 1e-6;

/// A collider acting on grid nodes.
#[derive(Debug, Clone, PartialEq)]
pub enum Collider {
    /// Nodes with `(x − point)·normal ≤ 1e-6` (m) are treated; `normal` points into the free side.
    HalfSpace {
        /// A point on the plane (m).
        point: DVec3,
        /// Unit normal (into the free region).
        normal: DVec3,
        /// Treatment.
        kind: BoundaryKind,
    },
    /// Nodes strictly inside the box are treated; normal = outward normal of the nearest face.
    Box {
        /// The box (m).
        aabb: Aabb,
        /// Treatment.
        kind: BoundaryKind,
    },
}

impl Collider {
    /// Ground plane `y = h` (m).
    pub fn ground(h: f64, kind: BoundaryKind) -> Self {
        Collider::HalfSpace {
            point: DVec3::new(0.0, h, 0.0),
            normal: DVec3::Y,
            kind,
        }
    }

    fn validate(&self) -> Result<(), MpmError> {
        match self {
            Collider::HalfSpace { point, normal, .. } => {
                if !point.is_finite() || !normal.is_finite() {
                    return Err(MpmError::NonFiniteInput {
                        field: "collider.point/normal",
                        index: 0,
                        value: f64::NAN,
                    });
                }
                if (normal.length() - 1.0).abs() > 1e-9 {
                    return Err(MpmError::InvalidParameter {
                        field: "collider.normal",
                        value: normal.length(),
                        reason: "normal must have unit length",
                    });
                }
            }
            Collider::Box { aabb, .. } => {
                if (aabb.hi - aabb.lo).min_element() <= 0.0 {
                    return Err(MpmError::InvalidParameter {
                        field: "collider.box",
                        value: (aabb.hi - aabb.lo).min_element(),
                        reason: "hi must exceed lo",
                    });
                }
            }
        }
        Ok(())
    }

    /// The normal of this collider at node `x`, or `None` if the node is not affected.
    #[inline]
    fn normal_at(&self, x: DVec3) -> Option<(DVec3, BoundaryKind)> {
        match *self {
            Collider::HalfSpace {
                point,
                normal,
                kind,
            } => ((x - point).dot(normal) <= PLANE_EPS).then_some((normal, kind)),
            Collider::Box { aabb, kind } => {
                if !(x.cmpgt(aabb.lo).all() && x.cmplt(aabb.hi).all()) {
                    return None;
                }
                let dlo = x - aabb.lo;
                let dhi = aabb.hi - x;
                let mut best = (dlo.x, -DVec3::X);
                for (d, n) in [
                    (dlo.y, -DVec3::Y),
                    (dlo.z, -DVec3::Z),
                    (dhi.x, DVec3::X),
                    (dhi.y, DVec3::Y),
                    (dhi.z, DVec3::Z),
                ] {
                    if d < best.0 {
                        best = (d, n);
                    }
                }
                Some((best.1, kind))
            }
        }
    }
}

#[inline]
fn project(v: DVec3, n: DVec3, kind: BoundaryKind) -> DVec3 {
    match kind {
        BoundaryKind::Sticky => DVec3::ZERO,
        BoundaryKind::Slip => v - v.dot(n) * n,
        BoundaryKind::Separate => {
            let vn = v.dot(n);
            if vn < 0.0 { v - vn * n } else { v }
        }
    }
}

/// Adjoint of [`project`] given the input velocity `v` (the decision) and the output gradient.
#[inline]
fn project_adjoint(v: DVec3, n: DVec3, kind: BoundaryKind, g: DVec3) -> DVec3 {
    match kind {
        BoundaryKind::Sticky => DVec3::ZERO,
        BoundaryKind::Slip => g - g.dot(n) * n,
        BoundaryKind::Separate => {
            if v.dot(n) < 0.0 {
                g - g.dot(n) * n
            } else {
                g
            }
        }
    }
}

/// All boundary conditions of a scene, applied in order: colliders, then the domain walls.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Boundaries {
    /// Colliders (ground, half-spaces, boxes).
    pub colliders: Vec<Collider>,
    /// Treatment of grid nodes outside the particle domain (None = no walls).
    pub walls: Option<BoundaryKind>,
}

impl Boundaries {
    /// Checks every collider.
    pub fn validate(&self) -> Result<(), MpmError> {
        self.colliders.iter().try_for_each(Collider::validate)
    }

    /// Wall normals (into the domain) at node `x`, up to one per axis.
    #[inline]
    fn wall_normals(grid: &GridSpec, x: DVec3) -> [Option<DVec3>; 3] {
        let d = grid.domain;
        let mut out = [None; 3];
        for (a, o) in out.iter_mut().enumerate() {
            if x[a] < d.lo[a] {
                let mut n = DVec3::ZERO;
                n[a] = 1.0;
                *o = Some(n);
            } else if x[a] > d.hi[a] {
                let mut n = DVec3::ZERO;
                n[a] = -1.0;
                *o = Some(n);
            }
        }
        out
    }

    /// Applies every condition to the velocity `v` (m/s) of the node at `x` (m).
    #[inline]
    pub fn apply(&self, grid: &GridSpec, x: DVec3, mut v: DVec3) -> DVec3 {
        for c in &self.colliders {
            if let Some((n, k)) = c.normal_at(x) {
                v = project(v, n, k);
            }
        }
        if let Some(kind) = self.walls {
            for n in Self::wall_normals(grid, x).into_iter().flatten() {
                v = project(v, n, kind);
            }
        }
        v
    }

    /// Adjoint of [`Self::apply`]: `v` is the node velocity before the conditions, `g` the
    /// gradient after them.
    pub fn adjoint(&self, grid: &GridSpec, x: DVec3, v: DVec3, mut g: DVec3) -> DVec3 {
        // Replay the chain to get each condition's input velocity.
        let mut stack: Vec<(DVec3, DVec3, BoundaryKind)> = Vec::new();
        let mut cur = v;
        for c in &self.colliders {
            if let Some((n, k)) = c.normal_at(x) {
                stack.push((cur, n, k));
                cur = project(cur, n, k);
            }
        }
        if let Some(kind) = self.walls {
            for n in Self::wall_normals(grid, x).into_iter().flatten() {
                stack.push((cur, n, kind));
                cur = project(cur, n, kind);
            }
        }
        for (vin, n, k) in stack.into_iter().rev() {
            g = project_adjoint(vin, n, k, g);
        }
        g
    }
}
