//! The vectorised engine: the same substep as [`crate::sim`] (PAC-NeRF's, fixture README §3)
//! with particles across SIMD lanes, in `f32` ([`crate::Precision::F32`], eight lanes) or
//! `f64` (four lanes).
//!
//! Particles are sorted by stencil base cell and cut into groups of one vector
//! ([`groups`]); a group's lanes share their 27 nodes, so P2G sums a node's contributions
//! across lanes and G2P broadcasts a node's velocity ([`transfer`]). The stress pass runs
//! whole vectors of consecutive particles ([`stress`]). The grid stays `f64` and goes through
//! the same grid update and boundary conditions as the scalar engine. Sums run in an order fixed
//! by the positions alone, so results are bit-identical for any thread count and instruction
//! set.

/// `[e(0), e(1), …, e(n − 1)]` built by a loop, not a closure: kernel code must stay in the
/// body of the function that carries the target features (`std::array::from_fn`'s closure
/// would be compiled without them, and every lane operation inside it would become a call).
macro_rules! arr {
    ($n:literal, |$k:ident| $e:expr) => {{
        let $k = 0usize;
        let first = $e;
        let mut out = [first; $n];
        #[allow(clippy::reversed_empty_ranges)]
        for $k in 1..$n {
            out[$k] = $e;
        }
        out
    }};
}

pub(crate) mod adjoint;
pub(crate) mod groups;
pub(crate) mod simd;
pub(crate) mod soa;
pub(crate) mod stress;
pub(crate) mod tape;
pub(crate) mod transfer;

#[cfg(test)]
mod tests;

use glam::{DVec3, IVec3};
use rayon::prelude::*;

use self::groups::{Groups, task_cuts};
use self::simd::{Precise, Real};
use self::soa::{C, F, Soa, V, padded};
use self::stress::{Kept, SlotMaterial, StressTask};
use self::transfer::{G2pOut, G2pTask, P2gTask};
use crate::boundary::Boundaries;
use crate::error::MpmError;
use crate::forces::{ParticleForce, extra_momentum};
use crate::grid::{GridSpec, NodeBox};
use crate::grid_update::mass_threshold;
use crate::isa::Isa;
use crate::models::{Constitutive, LaneKernel};
use crate::order::Order;
use crate::sim::{RunReport, Simulator};
use crate::state::{Material, State};

/// Particles per task of the stress pass (a multiple of every lane count).
pub(crate) const STRESS_CHUNK: usize = 1024;

/// Particles per task of G2P (about; tasks end on group boundaries).
pub(crate) const G2P_CHUNK: usize = 2048;

/// A run re-sorts its particles when they have broken into this many times the groups of the
/// last sort (as they move, runs of one cell get shorter).
const RESORT_GROWTH: f64 = 1.25;

/// `fields[k]` cut into the pieces `cuts[i]..cuts[i + 1]`, as one array of `K` pieces per
/// piece index.
pub(crate) fn split_fields<'a, T, const K: usize>(
    fields: [&'a mut [T]; K],
    cuts: &[usize],
) -> Vec<[&'a mut [T]; K]> {
    let mut per_field: Vec<std::vec::IntoIter<&'a mut [T]>> = fields
        .into_iter()
        .map(|mut f| {
            let mut out = Vec::with_capacity(cuts.len());
            let mut at = cuts[0];
            f = &mut f[at..];
            for &c in &cuts[1..] {
                let (piece, rest) = f.split_at_mut(c - at);
                out.push(piece);
                f = rest;
                at = c;
            }
            out.into_iter()
        })
        .collect();
    (0..cuts.len() - 1)
        .map(|_| std::array::from_fn(|k| per_field[k].next().expect("one piece per cut")))
        .collect()
}

/// `K` consecutive fields of a field-major buffer with `stride` entries per field, from `at`.
pub(crate) fn fields_mut<T, const K: usize>(
    data: &mut [T],
    stride: usize,
    at: usize,
) -> [&mut [T]; K] {
    let mut it = data[at * stride..(at + K) * stride].chunks_exact_mut(stride);
    std::array::from_fn(|_| it.next().expect("K fields"))
}

/// `K` consecutive fields of a field-major buffer, from `at`.
pub(crate) fn fields<T, const K: usize>(data: &[T], stride: usize, at: usize) -> [&[T]; K] {
    std::array::from_fn(|k| &data[(at + k) * stride..(at + k + 1) * stride])
}

/// Node velocities `[vx, vy, vz, 0]` (m/s, in `T`) from the accumulated `[mv, m]` of the
/// nodes of `active`, returning the largest velocity component (m/s): `v = mv/m + dt g` above the mass threshold, then the boundary
/// conditions (in `f64`, [`Boundaries::apply`]); 0 below it. The rest of `out` is left as it
/// was (nothing reads it).
#[allow(clippy::too_many_arguments)]
pub(crate) fn grid_update<T: Real>(
    grid: &GridSpec,
    nodes: &[[T; 4]],
    active: &NodeBox,
    dt: f64,
    g: glam::DVec3,
    bc: &Boundaries,
    out: &mut Vec<[T; 4]>,
) -> f64 {
    let thr = mass_threshold(grid.dx);
    out.resize(grid.len(), [T::of(0.0); 4]);
    let (layer, dz) = (grid.layer(), grid.dims[2]);
    let clear = bc.clear_axes(grid);
    out.par_chunks_mut(layer)
        .zip(nodes.par_chunks(layer))
        .enumerate()
        .skip(active.x.start)
        .take(active.x.len())
        .map(|(x, (out, nodes))| {
            let mut v_max = 0.0f64;
            for y in active.y.clone() {
                let row = y * dz + active.z.start..y * dz + active.z.end;
                let zs = active.z.clone();
                let clear_z = clear.as_ref().filter(|c| c[0][x] && c[1][y]).map(|c| &c[2]);
                for (z, (o, n)) in zs.zip(out[row.clone()].iter_mut().zip(&nodes[row])) {
                    let m = n[3].f64();
                    *o = if m > thr {
                        let mv = glam::DVec3::new(n[0].f64(), n[1].f64(), n[2].f64());
                        let v = mv / m + dt * g;
                        let v = if clear_z.is_some_and(|c| c[z]) {
                            v
                        } else {
                            bc.apply(grid, grid.node_pos([x, y, z]), v)
                        };
                        let vt = [T::of(v.x), T::of(v.y), T::of(v.z), T::of(0.0)];
                        v_max = v_max.max(vt.iter().fold(0.0, |a, c| a.max(c.f64().abs())));
                        vt
                    } else {
                        [T::of(0.0); 4]
                    };
                }
            }
            v_max
        })
        .reduce(|| 0.0, f64::max)
}

/// Starts of the chunks of `chunk` entries covering `0..len`, then `len`.
pub(crate) fn chunk_cuts(len: usize, chunk: usize) -> Vec<usize> {
    (0..len.div_ceil(chunk))
        .map(|k| k * chunk)
        .chain(std::iter::once(len))
        .collect()
}

/// The intermediates of one substep that its adjoint reads: the groups, `A`, τ and the
/// model's scalar (when kept), the forces' momentum and the grid.
#[derive(Debug)]
pub(crate) struct Work<T> {
    pub(crate) groups: Groups,
    /// The affine matrices `A` (9 fields).
    pub(crate) a: Vec<T>,
    /// τ (9 fields) and [`Constitutive::update_with_aux`]'s scalar, when kept.
    pub(crate) tau: Vec<T>,
    pub(crate) aux: Vec<T>,
    /// Extra momentum of the substep (3 fields), when forces act.
    pub(crate) extra: Option<Vec<T>>,
    /// The grid (a following grid's window) the groups and node arrays are laid out on.
    pub(crate) grid: GridSpec,
    /// `[mv, m]` per node (kg·m/s, kg), zero outside `active`.
    pub(crate) nodes: Vec<[T; 4]>,
    pub(crate) active: NodeBox,
    /// `[v, 0]` per node (m/s), and the largest component of any.
    pub(crate) vgrid: Vec<[T; 4]>,
    pub(crate) v_max: f64,
}

impl<T> Default for Work<T> {
    fn default() -> Self {
        Self {
            groups: Groups::default(),
            a: Vec::new(),
            tau: Vec::new(),
            aux: Vec::new(),
            extra: None,
            grid: GridSpec::empty(),
            nodes: Vec::new(),
            active: NodeBox::default(),
            vgrid: Vec::new(),
            v_max: 0.0,
        }
    }
}

impl<T: Real> Work<T> {
    /// Sized for `n` particles.
    fn fit(&mut self, n: usize, keep: bool, keep_tau: bool) {
        let st = padded(n);
        self.a = scratch(std::mem::take(&mut self.a), 9 * st);
        if keep {
            if keep_tau {
                self.tau = scratch(std::mem::take(&mut self.tau), 9 * st);
            }
            self.aux = scratch(std::mem::take(&mut self.aux), st);
        }
    }

    /// The node arrays laid out on `grid` (still zero outside `active`).
    fn set_grid(&mut self, grid: &GridSpec) {
        if self.grid != *grid {
            relayout(&mut self.nodes, &mut self.active, &self.grid, grid);
            self.vgrid.resize(grid.len(), [T::of(0.0); 4]);
            self.grid = *grid;
        }
    }
}

/// A node array that is zero outside `active` (laid out on `old`) laid out on `new`, still
/// zero outside `active`: the box is cleared first when the layout changes (a window of other
/// dimensions), and new entries are zero.
pub(crate) fn relayout<T: Real>(
    data: &mut Vec<[T; 4]>,
    active: &mut NodeBox,
    old: &GridSpec,
    new: &GridSpec,
) {
    if old.dims != new.dims {
        if data.len() == old.len() {
            active.fill(old, data, [T::of(0.0); 4]);
        } else {
            data.clear();
        }
        *active = NodeBox::default();
    }
    data.resize(new.len(), [T::of(0.0); 4]);
}

/// The window of a following grid over the particles of `p` (positions from `template`'s
/// anchor): the nodes of their stencils, `⌊x/dx − ½⌋ .. ⌊x/dx − ½⌋ + 2` on each axis, with one
/// node more on each side (a bound on the rounding of the key pass).
pub(crate) fn follow_window<T: Precise>(
    template: &GridSpec,
    p: &Soa<T>,
    max_nodes: usize,
) -> Result<GridSpec, MpmError> {
    let (n, st) = (p.n, p.stride);
    let inv = T::of(template.inv_dx);
    let half = T::of(0.5);
    let mut lo = IVec3::ZERO;
    let mut hi = IVec3::ZERO;
    let mut box_m = ([0.0; 3], [0.0; 3]);
    for a in 0..3 {
        let xs = &p.x[a * st..a * st + n];
        let (mn, mx) = xs
            .par_chunks(4096)
            .map(|c| {
                c.iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
                        let v = v.f64();
                        (l.min(v), h.max(v))
                    })
            })
            .reduce(
                || (f64::INFINITY, f64::NEG_INFINITY),
                |x, y| (x.0.min(y.0), x.1.max(y.1)),
            );
        let base = |v: f64| (T::of(v) * inv - half).floor().f64();
        let (bl, bh) = (base(mn), base(mx));
        // Non-finite positions: the substep reports them; keep a valid window meanwhile.
        let (bl, bh) = if bl.is_finite() && bh.is_finite() && bl.abs() < 1e9 && bh.abs() < 1e9 {
            (bl, bh)
        } else {
            (0.0, 0.0)
        };
        lo[a] = template.anchor[a] + bl as i32 - 1;
        hi[a] = template.anchor[a] + bh as i32 + 3;
        box_m.0[a] = mn + template.anchor[a] as f64 * template.dx;
        box_m.1[a] = mx + template.anchor[a] as f64 * template.dx;
    }
    let win = template.window(lo, hi, template.anchor);
    let nodes = win.dims.iter().map(|&d| d as f64).product::<f64>();
    if nodes > max_nodes as f64 {
        return Err(MpmError::GridTooLarge {
            substep: 0,
            lo: box_m.0,
            hi: box_m.1,
            nodes: nodes as usize,
            budget: max_nodes,
            dx: template.dx,
        });
    }
    Ok(win)
}

/// The engine's arrays, which the simulator keeps from one run to the next so that a run
/// reuses them instead of faulting in fresh pages (tens of MB at 100k particles).
#[derive(Debug)]
pub(crate) struct Buffers<T> {
    /// The state.
    p: Option<Soa<T>>,
    /// The buffer a re-sort or the write-back fills (then swapped with `p`).
    pub(crate) spare: Option<Soa<T>>,
    /// The positions the next substep writes (then swapped with `p.x`).
    x_next: Vec<T>,
    /// Per-particle mass, volume, μ, λ in slot order.
    mass: Vec<T>,
    volume: Vec<T>,
    mu: Vec<T>,
    lam: Vec<T>,
    /// The current substep's intermediates.
    work: Work<T>,
}

impl<T> Default for Buffers<T> {
    fn default() -> Self {
        Self {
            p: None,
            spare: None,
            x_next: Vec::new(),
            mass: Vec::new(),
            volume: Vec::new(),
            mu: Vec::new(),
            lam: Vec::new(),
            work: Work::default(),
        }
    }
}

/// `v` resized to `len` entries (contents unspecified: every entry is written before use).
fn scratch<T: Real>(mut v: Vec<T>, len: usize) -> Vec<T> {
    if v.len() != len {
        v = vec![T::of(0.0); len];
    }
    v
}

/// `src` copied into `v`, padded with `pad` like the state arrays.
fn fill_padded<T: Real>(v: &mut Vec<T>, src: &[f64], pad: f64) {
    v.clear();
    v.extend(src.iter().map(|&x| T::of(x)));
    v.resize(padded(src.len()), T::of(pad));
}

/// An empty material.
fn no_material() -> Material {
    Material {
        mass: Vec::new(),
        volume: Vec::new(),
        mu: Vec::new(),
        lam: Vec::new(),
        family: Vec::new(),
    }
}

/// The vectorised engine in precision `T` for one simulator: the state (slot order), the
/// per-particle material in the same order, and the buffers.
pub(crate) struct Engine<'s, T, M: Constitutive> {
    pub(crate) sim: &'s Simulator<M>,
    /// The node particle positions are measured from (a fixed grid's first node, or the
    /// anchor of a following grid's windows), and its position (m).
    pub(crate) anchor: IVec3,
    pub(crate) origin: DVec3,
    /// The domain relative to `origin`, rounded inwards (m).
    pub(crate) lo: [T; 3],
    pub(crate) hi: [T; 3],
    /// Slot `i` holds the caller's particle `ids[i]`; particle `p` sits in slot `rank[p]`.
    pub(crate) ids: Vec<u32>,
    pub(crate) rank: Vec<u32>,
    pub(crate) p: Soa<T>,
    b: Buffers<T>,
    /// The caller's material, and the same in slot order (`f64`, kept for the per-particle
    /// models only).
    caller_mat: Material,
    mat: Material,
    /// Whether every particle has the same mass, volume, μ and λ.
    uniform: bool,
    /// The caller's forces and impulses, and the same renumbered to slots.
    forces: Vec<ParticleForce>,
    slot_forces: Vec<ParticleForce>,
    /// Groups right after the last sort.
    sorted_groups: usize,
    /// Whether the stress pass keeps τ and the model's scalar (for an adjoint).
    pub(crate) keep: bool,
    /// Substep (s): the simulator's, or a [`crate::Stepper`]'s frame's.
    pub(crate) dt: f64,
}

impl<'s, T: Precise, M: Constitutive> Engine<'s, T, M> {
    /// Whether an adjoint needs τ kept (the per-particle models; the lane models' adjoints
    /// recompute it).
    const KEEP_TAU: bool = matches!(M::LANE_KERNEL, LaneKernel::PerParticle);

    /// The engine loaded with `state` (validated, positions inside the domain) and `mat`,
    /// particles sorted by cell, in the buffers `b` (a previous run's, or empty).
    pub(crate) fn new(
        sim: &'s Simulator<M>,
        state: &State,
        mat: &Material,
        mut b: Buffers<T>,
    ) -> Self {
        let anchor = if sim.grid.follows() {
            // The node below the particles' box.
            let lo = state.x.iter().fold(DVec3::INFINITY, |l, x| l.min(*x));
            (lo * sim.grid.inv_dx).floor().as_ivec3()
        } else {
            sim.grid.origin
        };
        let origin = anchor.as_dvec3() * sim.grid.dx;
        // In the caller's order first; sorted below.
        let p = Soa::from_state(state, origin, b.p.take());
        let ids = (0..state.len() as u32).collect();
        let mut e = Self::with_state(sim, anchor, p, ids, mat, b);
        e.resort();
        e
    }

    /// The engine loaded with the state `p` in slot order `ids` (slot `i` holds the caller's
    /// particle `ids[i]`; positions relative to node `anchor`) and `mat` (the caller's order),
    /// in the buffers `b`; groups built.
    pub(crate) fn with_state(
        sim: &'s Simulator<M>,
        anchor: IVec3,
        p: Soa<T>,
        ids: Vec<u32>,
        mat: &Material,
        mut b: Buffers<T>,
    ) -> Self {
        let grid = &sim.grid;
        let origin = anchor.as_dvec3() * grid.dx;
        // A following grid has no domain: ±∞ hold nothing.
        let lo_l = grid.domain.lo - origin;
        let hi_l = grid.domain.hi - origin;
        let n = p.n;
        b.x_next = scratch(std::mem::take(&mut b.x_next), 3 * padded(n));
        b.work.fit(n, false, false);
        let same = |v: &[f64]| v.iter().all(|&x| x == v[0]);
        let uniform = [&mat.mass, &mat.volume, &mat.mu, &mat.lam]
            .into_iter()
            .all(|v| same(v))
            && mat.family.is_empty();
        let mut e = Self {
            sim,
            anchor,
            origin,
            lo: std::array::from_fn(|a| T::of_up(lo_l[a])),
            hi: std::array::from_fn(|a| T::of_down(hi_l[a])),
            ids: Vec::new(),
            rank: Vec::new(),
            p,
            b,
            caller_mat: mat.clone(),
            mat: no_material(),
            uniform,
            forces: sim.config.forces.clone(),
            slot_forces: Vec::new(),
            sorted_groups: 0,
            keep: false,
            dt: sim.config.dt,
        };
        e.set_order(ids);
        // A window too large stops the first substep, which computes it again.
        if e.place_grid(None).is_ok() {
            let grid = e.b.work.grid;
            e.b.work.groups.rebuild(&grid, &e.p);
        }
        e
    }

    /// The grid of a substep from the state `src` (else the engine's own): the fixed grid, or
    /// the window of a following grid over its particles; the work arrays are laid out on it.
    fn place_grid(&mut self, src: Option<&Soa<T>>) -> Result<(), MpmError> {
        let grid = match self.sim.config.domain {
            crate::sim::Domain::Fixed(_) => self.sim.grid,
            crate::sim::Domain::Follow { max_nodes } => {
                let mut template = self.sim.grid;
                template.anchor = self.anchor;
                follow_window(&template, src.unwrap_or(&self.p), max_nodes)?
            }
        };
        self.b.work.set_grid(&grid);
        Ok(())
    }

    /// The spare buffers of a state of `n` particles (from the buffers' own, else new).
    pub(crate) fn soa_from(b: &mut Buffers<T>, src: &Soa<T>) -> Soa<T> {
        match b.p.take().filter(|p| p.n == src.n) {
            Some(mut p) => {
                p.x.copy_from_slice(&src.x);
                p.vcf.copy_from_slice(&src.vcf);
                p
            }
            None => src.clone(),
        }
    }

    /// Slot `i` holds the caller's particle `ids[i]`: ranks, per-particle material and forces
    /// follow.
    fn set_order(&mut self, ids: Vec<u32>) {
        let order = Order::from_slots(ids);
        let cm = &self.caller_mat;
        let b = &mut self.b;
        for (v, src) in [
            (&mut b.mass, &cm.mass),
            (&mut b.volume, &cm.volume),
            (&mut b.mu, &cm.mu),
            (&mut b.lam, &cm.lam),
        ] {
            if self.uniform {
                fill_padded(v, &src[..1], src[0]);
            } else {
                fill_padded(v, &order.gather(src), 0.0);
            }
        }
        // The per-particle models read the f64 material.
        if M::LANE_KERNEL == LaneKernel::PerParticle || !cm.family.is_empty() {
            self.mat = order.sort_material(cm);
        }
        if !self.forces.is_empty() {
            self.slot_forces = order.sort_forces(&self.forces);
        }
        self.rank = order.ranks().to_vec();
        self.ids = order.slots().to_vec();
    }

    /// Takes the slot order `ids` of a checkpoint of `n` particles (the state itself is not
    /// copied: the backward pass loads each substep's state before using it).
    pub(crate) fn load(&mut self, n: usize, ids: &[u32]) {
        if self.p.n != n {
            self.p = Soa::new(n);
        }
        if self.ids != ids {
            self.set_order(ids.to_vec());
        }
        self.b.work.fit(n, self.keep, Self::KEEP_TAU);
    }

    /// The buffers, for the next run.
    pub(crate) fn into_buffers(mut self) -> Buffers<T> {
        self.take_buffers()
    }

    /// The buffers, for the next run (the engine is left empty).
    pub(crate) fn take_buffers(&mut self) -> Buffers<T> {
        let mut b = std::mem::take(&mut self.b);
        b.p = Some(std::mem::replace(&mut self.p, Soa::empty()));
        b
    }

    /// Re-sorts the particles by their current cells (the groups' keys).
    fn resort(&mut self) {
        let Some(rel) = Order::by_key(&self.b.work.groups.key, self.b.work.grid.len()) else {
            return;
        };
        let from = rel.slots();
        let mut next = self.spare();
        self.p.permute_into(from, &mut next);
        self.b.spare = Some(std::mem::replace(&mut self.p, next));
        let ids = from.iter().map(|&i| self.ids[i as usize]).collect();
        self.set_order(ids);
        let grid = self.b.work.grid;
        self.b.work.groups.rebuild(&grid, &self.p);
    }

    /// The spare state buffer (allocated when there is none of this size).
    fn spare(&mut self) -> Soa<T> {
        let n = self.p.n;
        self.b
            .spare
            .take()
            .filter(|s| s.n == n)
            .unwrap_or_else(|| Soa::new(n))
    }

    /// Writes the particles back into `state` (the caller's order), positions clamped into
    /// the domain (they were held there in `T`; the shift back may round a last bit out).
    pub(crate) fn write_back(&self, state: &mut State) {
        self.read(state, false);
    }

    /// [`Self::write_back`] of `x` and `v` alone when `motion_only`.
    pub(crate) fn read(&self, state: &mut State, motion_only: bool) {
        self.p.to_state(&self.rank, self.origin, state, motion_only);
        let grid = &self.sim.grid;
        state.x.par_iter_mut().for_each(|x| {
            if x.is_finite() {
                grid.hold(x);
            }
        });
    }

    /// Grid and groups of the current positions; with `resort`, sorts again first when they
    /// have broken up ([`RESORT_GROWTH`]). Fails when a following grid's window would exceed
    /// its budget ([`MpmError::GridTooLarge`], substep 0: the caller names it).
    pub(crate) fn regroup(&mut self, resort: bool) -> Result<(), MpmError> {
        self.regroup_from(None, resort)
    }

    /// [`Self::regroup`] of the positions of `src` (the state the next substep reads) when
    /// given, else of the engine's own.
    pub(crate) fn regroup_from(
        &mut self,
        src: Option<&Soa<T>>,
        resort: bool,
    ) -> Result<(), MpmError> {
        self.place_grid(src)?;
        let grid = self.b.work.grid;
        self.b.work.groups.rebuild(&grid, src.unwrap_or(&self.p));
        let groups = self.b.work.groups.list.len();
        if self.sorted_groups == 0 {
            self.sorted_groups = groups;
        } else if resort && groups as f64 > RESORT_GROWTH * self.sorted_groups as f64 {
            self.resort();
            self.sorted_groups = self.b.work.groups.list.len();
        }
        Ok(())
    }

    /// Steps 1–4 for every particle: `F` (in place, or from `src` into the engine's state),
    /// `A`, and τ with the model's scalar when [`Self::keep`]; returns whether some new `F` is
    /// NaN/Inf.
    fn stress(&mut self, isa: Isa, src: Option<&Soa<T>>) -> bool {
        let sim = self.sim;
        let grid = &sim.grid;
        let (n, st, dt) = (self.p.n, self.p.stride, self.dt);
        let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
        let (head, tail) = self.p.vcf.split_at_mut(F * st);
        let (c, f0): ([&[T]; 9], Option<[&[T]; 9]>) = match src {
            Some(s) => (fields(&s.vcf, st, C), Some(fields(&s.vcf, st, F))),
            None => (fields(head, st, C), None),
        };
        let f: [&mut [T]; 9] = fields_mut(tail, st, 0);
        let b = &mut self.b;
        let work = &mut b.work;
        let cuts = chunk_cuts(st, STRESS_CHUNK);
        let a = split_fields(fields_mut::<T, 9>(&mut work.a, st, 0), &cuts);
        let kept: Vec<Kept<'_, T>> = if self.keep {
            let taus: Vec<Option<[&mut [T]; 9]>> = if Self::KEEP_TAU {
                split_fields(fields_mut::<T, 9>(&mut work.tau, st, 0), &cuts)
                    .into_iter()
                    .map(Some)
                    .collect()
            } else {
                (0..cuts.len() - 1).map(|_| None).collect()
            };
            taus.into_iter()
                .zip(work.aux.chunks_mut(STRESS_CHUNK))
                .map(Some)
                .collect()
        } else {
            (0..cuts.len() - 1).map(|_| None).collect()
        };
        let model = &sim.model;
        let mat = SlotMaterial::new([&b.mass, &b.volume, &b.mu, &b.lam], &self.mat, self.uniform);
        split_fields(f, &cuts)
            .into_par_iter()
            .zip(a)
            .zip(kept)
            .enumerate()
            .map(|(k, ((f, a), keep))| {
                let r = cuts[k]..cuts[k + 1];
                let real = n.saturating_sub(r.start).min(r.len());
                isa.run_wide(StressTask {
                    model,
                    dt,
                    d_inv,
                    real,
                    c: c.map(|x| &x[r.clone()]),
                    mat: mat.slots(r.clone(), real),
                    f0: f0.map(|f0| f0.map(|x| &x[r.clone()])),
                    f,
                    a,
                    keep,
                })
            })
            .reduce(|| false, |x, y| x | y)
    }

    /// Steps 5–6: P2G of `x, v, A` (and the forces' momentum at time `t`) into the nodes of
    /// the particles' box, then the grid update.
    fn particles_to_grid(&mut self, isa: Isa, t: f64, src: Option<&Soa<T>>) {
        let sim = self.sim;
        let grid = self.b.work.grid;
        let grid = &grid;
        let (n, st) = (self.p.n, self.p.stride);
        let dt = self.dt;
        let b = &mut self.b;
        let work = &mut b.work;
        work.extra = extra_momentum(&self.slot_forces, n, t, dt).map(|e| {
            let mut out = std::mem::take(&mut work.extra).unwrap_or_default();
            out.clear();
            out.resize(3 * st, T::of(0.0));
            for (i, m) in e.iter().enumerate() {
                for d in 0..3 {
                    out[d * st + i] = T::of(m[d]);
                }
            }
            out
        });
        work.active.fill(grid, &mut work.nodes, [T::of(0.0); 4]);
        work.active = work.groups.touched.clone();
        let s = src.unwrap_or(&self.p);
        let x: [&[T]; 3] = fields(&s.x, st, 0);
        let v: [&[T]; 3] = fields(&s.vcf, st, V);
        let a: [&[T]; 9] = fields(&work.a, st, 0);
        let extra = work.extra.as_ref().map(|e| fields::<T, 3>(e, st, 0));
        let mass = &b.mass;
        let uniform_mass = self.uniform;
        work.groups
            .scatter(grid, &mut work.nodes, |groups, piece, first| {
                isa.run_wide(P2gTask {
                    grid,
                    groups,
                    x,
                    v,
                    a,
                    mass,
                    uniform_mass,
                    extra,
                    piece,
                    first,
                })
            });
        work.v_max = grid_update(
            grid,
            &work.nodes,
            &work.active,
            dt,
            sim.config.gravity,
            &sim.config.boundaries,
            &mut work.vgrid,
        );
    }

    /// Step 7: G2P, `x ← hold(x + dt v)` (into `x_next`, then swapped in); returns the
    /// particles held and whether some new value is NaN/Inf.
    fn g2p(&mut self, isa: Isa, src: Option<&Soa<T>>) -> (usize, bool) {
        let grid = self.b.work.grid;
        let grid = &grid;
        let (n, st) = (self.p.n, self.p.stride);
        let tasks = self.b.work.groups.tasks(G2P_CHUNK);
        let cuts = task_cuts(&tasks, n);
        let x: [&mut [T]; 3] = fields_mut(&mut self.b.x_next, st, 0);
        let (x_own, vcf) = (&self.p.x, &mut self.p.vcf);
        let x_old: [&[T]; 3] = fields(src.map_or(x_own, |s| &s.x), st, 0);
        let (vc, _) = vcf.split_at_mut(F * st);
        let vc: [&mut [T]; 12] = fields_mut(vc, st, 0);
        let [v0, v1, v2, c0, c1, c2, c3, c4, c5, c6, c7, c8] = vc;
        let vgrid = bytemuck::cast_slice(&self.b.work.vgrid);
        let (lo, hi, dt) = (self.lo, self.hi, self.dt);
        let out = split_fields(x, &cuts)
            .into_par_iter()
            .zip(split_fields([v0, v1, v2], &cuts))
            .zip(split_fields([c0, c1, c2, c3, c4, c5, c6, c7, c8], &cuts))
            .zip(tasks)
            .map(|(((x, v), c), (groups, s0, _))| {
                isa.run_wide(G2pTask {
                    grid,
                    groups,
                    s0,
                    x_old,
                    vgrid,
                    dt,
                    lo,
                    hi,
                    out: G2pOut { x, v, c },
                })
            })
            .reduce(|| (0, false), |a, b| (a.0 + b.0, a.1 | b.1));
        std::mem::swap(&mut self.p.x, &mut self.b.x_next);
        out
    }

    /// Steps 1–6 of the substep at time `t` from the current groups: the intermediates of
    /// the substep in the work buffers, `F` updated; returns whether some new `F` is NaN/Inf.
    pub(crate) fn grid_step(&mut self, t: f64) -> bool {
        self.grid_from(t, None)
    }

    /// [`Self::grid_step`] reading the state `src` when given (the new `F` goes to the
    /// engine's state).
    pub(crate) fn grid_from(&mut self, t: f64, src: Option<&Soa<T>>) -> bool {
        let isa = Isa::detect();
        let bad = self.stress(isa, src);
        self.particles_to_grid(isa, t, src);
        bad
    }

    /// One substep at time `t` (s) from the current groups ([`Self::regroup`]); returns the
    /// particles held at the domain edge and whether some new value is NaN/Inf.
    pub(crate) fn step(&mut self, t: f64) -> (usize, bool) {
        self.step_from(t, None)
    }

    /// [`Self::step`] from the state `src` (its groups already built) into the engine's state
    /// when given: every field of the engine's state is written, so it needs no copy first.
    pub(crate) fn step_from(&mut self, t: f64, src: Option<&Soa<T>>) -> (usize, bool) {
        let bad_f = self.grid_from(t, src);
        let (held, bad) = self.g2p(Isa::detect(), src);
        (held, bad || bad_f)
    }

    /// The grid of the current substep (a following grid's window).
    pub(crate) fn grid(&self) -> &GridSpec {
        &self.b.work.grid
    }

    /// Counts substep `k`'s `(held, bad)` into `rep`; when some value went NaN/Inf, names the
    /// first offending particle.
    pub(crate) fn record(
        &self,
        k: usize,
        (held, bad): (usize, bool),
        rep: &mut RunReport,
    ) -> Result<(), MpmError> {
        if bad {
            let mut s = State::at_rest(vec![DVec3::ZERO; self.p.n]);
            self.write_back(&mut s);
            let (quantity, particle) = s.first_non_finite().unwrap_or(("x", 0));
            return Err(MpmError::NonFinite {
                substep: k,
                quantity,
                particle,
            });
        }
        // A following grid has no walls to stop a runaway: a node faster than a cell per
        // substep is a divergence (automatic substeps keep it under 0.3).
        let cells = self.b.work.v_max * self.dt * self.sim.grid.inv_dx;
        if self.sim.grid.follows() && cells > 1.0 {
            return Err(MpmError::Diverged {
                substep: k,
                speed: self.b.work.v_max,
                cells,
            });
        }
        rep.substeps += 1;
        rep.held += held;
        rep.max_held = rep.max_held.max(held);
        Ok(())
    }

    /// Marks the particles (the caller's indices) whose stencils reach a node each boundary
    /// treats in the current substep: `marks[c]` for collider `c`, then `marks[colliders]` for
    /// the domain walls.
    pub(crate) fn mark_contacts(&self, marks: &mut [Vec<bool>]) {
        let work = &self.b.work;
        let grid = &work.grid;
        let bc = &self.sim.config.boundaries;
        let dx = grid.dx;
        // Nothing to do when no boundary reaches the particles' box.
        let corner = |b: [usize; 3], k: usize| {
            (grid.origin.as_dvec3()
                + DVec3::new(b[0] as f64, b[1] as f64, b[2] as f64)
                + DVec3::splat(k as f64))
                * dx
        };
        let t = &work.groups.touched;
        if t.x.is_empty() {
            return;
        }
        let (blo, bhi) = (
            corner([t.x.start, t.y.start, t.z.start], 0),
            corner([t.x.end - 1, t.y.end - 1, t.z.end - 1], 0),
        );
        let n_col = bc.colliders.len();
        for (c, marks) in marks.iter_mut().enumerate() {
            let reaches = |lo: DVec3, hi: DVec3| match bc.colliders.get(c) {
                Some(col) => col.reaches(lo, hi, dx),
                None => c == n_col && bc.walls_reach(grid, lo, hi),
            };
            if !reaches(blo, bhi) {
                continue;
            }
            for g in &work.groups.list {
                let lo = corner(g.base.map(|b| b as usize), 0);
                if reaches(lo, lo + DVec3::splat(2.0 * dx)) {
                    for &id in &self.ids[g.start as usize..(g.start + g.n) as usize] {
                        marks[id as usize] = true;
                    }
                }
            }
        }
    }

    /// The work buffers, replaced by `with` (a spare set, or empty).
    pub(crate) fn take_work(&mut self, with: Work<T>) -> Work<T> {
        let w = std::mem::replace(&mut self.b.work, with);
        self.b.work.fit(self.p.n, self.keep, Self::KEEP_TAU);
        // The next substep lays the work out on its grid; until then, the one taken.
        self.b.work.set_grid(&w.grid);
        w
    }

    /// The work buffers.
    pub(crate) fn work(&self) -> &Work<T> {
        &self.b.work
    }

    /// The per-particle material in slot order (padded; one value each when uniform).
    pub(crate) fn material(&self) -> SlotMaterial<'_, T> {
        let b = &self.b;
        SlotMaterial::new([&b.mass, &b.volume, &b.mu, &b.lam], &self.mat, self.uniform)
    }
}
