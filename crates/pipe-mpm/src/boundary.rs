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
    /// An anchor: the nodes at `x` whose cell `round(x / cell)` (integer coordinates on a
    /// lattice of edge `cell`, m) is in `cells` are held still (sticky). It holds a simulated
    /// part where it joins parts that do not simulate (a leaf on its stem), as PhysDreamer
    /// freezes the grid next to the still points.
    Anchor {
        /// The held cells.
        cells: std::sync::Arc<std::collections::HashSet<[i32; 3]>>,
        /// Their lattice's edge (m).
        cell: f64,
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
            Collider::Anchor { cell, .. } => {
                if !(cell.is_finite() && *cell > 0.0) {
                    return Err(MpmError::InvalidParameter {
                        field: "collider.anchor.cell",
                        value: *cell,
                        reason: "must be finite and > 0",
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
            Collider::Anchor { ref cells, cell } => {
                let k = (x / cell).round();
                cells
                    .contains(&[k.x as i32, k.y as i32, k.z as i32])
                    .then_some((DVec3::Y, BoundaryKind::Sticky))
            }
        }
    }
}

impl Collider {
    /// Whether some node of the box of nodes `lo ..= hi` (m, on a lattice of cell `dx`) is
    /// one this collider treats.
    pub fn reaches(&self, lo: DVec3, hi: DVec3, dx: f64) -> bool {
        match *self {
            Collider::HalfSpace { point, normal, .. } => {
                // The smallest (x − p)·n over the box is at a corner.
                let corner = DVec3::select(normal.cmpgt(DVec3::ZERO), lo, hi);
                (corner - point).dot(normal) <= PLANE_EPS
            }
            Collider::Box { aabb, .. } => (0..3).all(|a| {
                // Some node strictly inside on this axis.
                (0..=((hi[a] - lo[a]) / dx).round() as i64)
                    .map(|k| lo[a] + k as f64 * dx)
                    .any(|x| x > aabb.lo[a] && x < aabb.hi[a])
            }),
            Collider::Anchor { ref cells, cell } => {
                let (a, b) = ((lo / cell).round(), (hi / cell).round());
                cells
                    .iter()
                    .any(|c| (0..3).all(|i| f64::from(c[i]) >= a[i] && f64::from(c[i]) <= b[i]))
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

    /// Which node indices along each axis lie clear of every condition that acts along that
    /// axis (`[x, y, z]`, one flag per index of `grid.dims`): a node whose three indices are
    /// clear is untouched by [`Self::apply`], so the grid update skips it. `None` when a
    /// collider depends on more than one coordinate (a box, a tilted plane): every node then
    /// goes through [`Self::apply`].
    ///
    /// The domain walls act along one axis each; a half-space whose normal has one non-zero
    /// component acts along that axis alone (the other terms of `(x − p)·n` are exactly 0).
    pub(crate) fn clear_axes(&self, grid: &GridSpec) -> Option<[Vec<bool>; 3]> {
        let axis_of = |n: DVec3| {
            let nonzero: Vec<usize> = (0..3).filter(|&a| n[a] != 0.0).collect();
            (nonzero.len() == 1).then(|| nonzero[0])
        };
        let mut planes = Vec::new();
        for c in &self.colliders {
            match c {
                Collider::HalfSpace { normal, .. } => planes.push((axis_of(*normal)?, c)),
                Collider::Box { .. } | Collider::Anchor { .. } => return None,
            }
        }
        Some(std::array::from_fn(|a| {
            (0..grid.dims[a])
                .map(|i| {
                    let mut l = [0; 3];
                    l[a] = i;
                    // The node's position; only its component `a` matters below.
                    let x = grid.node_pos(l);
                    let wall = self.walls.is_some() && Self::wall_normals(grid, x)[a].is_some();
                    let plane = planes
                        .iter()
                        .any(|&(b, c)| b == a && c.normal_at(x).is_some());
                    !(wall || plane)
                })
                .collect()
        }))
    }

    /// Whether the domain walls treat some node of the box of nodes `lo ..= hi` (m) of `grid`.
    pub fn walls_reach(&self, grid: &GridSpec, lo: DVec3, hi: DVec3) -> bool {
        self.walls.is_some() && (lo.cmplt(grid.domain.lo).any() || hi.cmpgt(grid.domain.hi).any())
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Every node of a grid: the nodes [`Boundaries::clear_axes`] calls clear must be left as
    /// they are by [`Boundaries::apply`] for velocities in every direction. Returns the clear
    /// nodes and the untouched ones.
    fn check_clear_axes(bc: &Boundaries, grid: &GridSpec) -> (usize, usize) {
        let clear = bc.clear_axes(grid).expect("separable conditions");
        let (mut n_clear, mut n_untouched) = (0, 0);
        for x in 0..grid.dims[0] {
            for y in 0..grid.dims[1] {
                for z in 0..grid.dims[2] {
                    let p = grid.node_pos([x, y, z]);
                    let touched = [-1.0, 1.0].into_iter().any(|s| {
                        [DVec3::X, DVec3::Y, DVec3::Z, DVec3::ONE]
                            .into_iter()
                            .any(|d| bc.apply(grid, p, s * d) != s * d)
                    });
                    let is_clear = clear[0][x] && clear[1][y] && clear[2][z];
                    assert!(!(is_clear && touched), "node {x} {y} {z} at {p} is changed");
                    n_clear += usize::from(is_clear);
                    n_untouched += usize::from(!touched);
                }
            }
        }
        (n_clear, n_untouched)
    }

    #[test]
    fn clear_axes_are_exactly_the_untouched_nodes() {
        let domain = Aabb::new(DVec3::new(0.1, 0.0, -0.2), DVec3::new(0.9, 0.7, 0.4));
        let grid = GridSpec::new(domain, 0.05, 3).unwrap();
        let plane = |point: DVec3, normal: DVec3, kind| Collider::HalfSpace {
            point,
            normal,
            kind,
        };
        // Without walls and colliders, every node is clear.
        let none = Boundaries {
            colliders: Vec::new(),
            walls: None,
        };
        assert_eq!(check_clear_axes(&none, &grid), (grid.len(), grid.len()));
        for kind in [
            BoundaryKind::Sticky,
            BoundaryKind::Slip,
            BoundaryKind::Separate,
        ] {
            let bc = Boundaries {
                colliders: vec![
                    Collider::ground(0.2, kind),
                    plane(DVec3::new(0.8, 0.0, 0.0), -DVec3::X, kind),
                ],
                walls: Some(kind),
            };
            let (n_clear, n_untouched) = check_clear_axes(&bc, &grid);
            // Inside the walls, above the ground, left of the plane: x 0.10–0.75, y 0.25–0.65
            // (the node at 14 dx rounds just above 0.7, outside the wall), z −0.20–0.40.
            assert_eq!(n_clear, 14 * 9 * 13, "of {}", grid.len());
            // Sticky changes every velocity it acts on: the clear nodes are all the untouched.
            if kind == BoundaryKind::Sticky {
                assert_eq!(n_clear, n_untouched);
            }
        }
        // A box or a tilted plane depends on several coordinates: no clear axes.
        let tilted = Boundaries {
            colliders: vec![plane(
                DVec3::ZERO,
                DVec3::new(0.6, 0.8, 0.0),
                BoundaryKind::Slip,
            )],
            walls: None,
        };
        assert!(tilted.clear_axes(&grid).is_none());
        let boxed = Boundaries {
            colliders: vec![Collider::Box {
                aabb: Aabb::new(DVec3::splat(0.3), DVec3::splat(0.5)),
                kind: BoundaryKind::Sticky,
            }],
            walls: Some(BoundaryKind::Slip),
        };
        assert!(boxed.clear_axes(&grid).is_none());
        let anchored = Boundaries {
            colliders: vec![anchor(&[[6, 4, 2]], 0.05)],
            walls: None,
        };
        assert!(anchored.clear_axes(&grid).is_none());
    }

    fn anchor(cells: &[[i32; 3]], cell: f64) -> Collider {
        Collider::Anchor {
            cells: std::sync::Arc::new(cells.iter().copied().collect()),
            cell,
        }
    }

    /// An anchor holds exactly the nodes of its cells still, whatever their velocity, and
    /// reaches a box of nodes only when one of its cells lies in it.
    #[test]
    fn an_anchor_holds_the_nodes_of_its_cells_only() {
        let grid = GridSpec::new(Aabb::new(DVec3::ZERO, DVec3::splat(0.5)), 0.05, 2).unwrap();
        let bc = Boundaries {
            colliders: vec![anchor(&[[3, 4, 5], [3, 5, 5]], 0.05)],
            walls: None,
        };
        assert!(bc.validate().is_ok());
        let mut held = 0;
        for x in 0..grid.dims[0] {
            for y in 0..grid.dims[1] {
                for z in 0..grid.dims[2] {
                    let p = grid.node_pos([x, y, z]);
                    let v = DVec3::new(0.3, -1.0, 0.2);
                    let k = (p / 0.05).round();
                    let inside = k.x == 3.0 && (k.y == 4.0 || k.y == 5.0) && k.z == 5.0;
                    let out = bc.apply(&grid, p, v);
                    assert_eq!(out, if inside { DVec3::ZERO } else { v }, "{p}");
                    held += usize::from(inside);
                }
            }
        }
        assert_eq!(held, 2);
        let c = &bc.colliders[0];
        assert!(c.reaches(DVec3::splat(0.1), DVec3::splat(0.3), 0.05));
        assert!(!c.reaches(DVec3::splat(0.3), DVec3::splat(0.45), 0.05));
        assert!(anchor(&[], 0.0).validate().is_err());
    }
}
