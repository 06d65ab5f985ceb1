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

pub(crate) mod groups;
pub(crate) mod simd;
pub(crate) mod soa;
pub(crate) mod stress;
pub(crate) mod transfer;

#[cfg(test)]
mod tests;

use glam::DVec3;
use rayon::prelude::*;

use self::groups::Groups;
use self::simd::{Precise, Real};
use self::soa::{C, F, Soa, V, padded};
use self::stress::StressTask;
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
const STRESS_CHUNK: usize = 1024;

/// Particles per task of G2P (about; tasks end on group boundaries).
const G2P_CHUNK: usize = 2048;

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
fn fields_mut<T, const K: usize>(data: &mut [T], stride: usize, at: usize) -> [&mut [T]; K] {
    let mut it = data[at * stride..(at + K) * stride].chunks_exact_mut(stride);
    std::array::from_fn(|_| it.next().expect("K fields"))
}

/// `K` consecutive fields of a field-major buffer, from `at`.
fn fields<T, const K: usize>(data: &[T], stride: usize, at: usize) -> [&[T]; K] {
    std::array::from_fn(|k| &data[(at + k) * stride..(at + k + 1) * stride])
}

/// Node velocities `[vx, vy, vz, 0]` (m/s, in `T`) from the accumulated `[mv, m]` of the
/// nodes of `active`: `v = mv/m + dt g` above the mass threshold, then the boundary
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
) {
    let thr = mass_threshold(grid.dx);
    out.resize(grid.len(), [T::of(0.0); 4]);
    let (layer, dz) = (grid.layer(), grid.dims[2]);
    out.par_chunks_mut(layer)
        .zip(nodes.par_chunks(layer))
        .enumerate()
        .skip(active.x.start)
        .take(active.x.len())
        .for_each(|(x, (out, nodes))| {
            for y in active.y.clone() {
                let row = y * dz..(y + 1) * dz;
                for (z, (o, n)) in out[row.clone()].iter_mut().zip(&nodes[row]).enumerate() {
                    let m = n[3].f64();
                    *o = if m > thr {
                        let mv = glam::DVec3::new(n[0].f64(), n[1].f64(), n[2].f64());
                        let v = bc.apply(grid, grid.node_pos([x, y, z]), mv / m + dt * g);
                        [T::of(v.x), T::of(v.y), T::of(v.z), T::of(0.0)]
                    } else {
                        [T::of(0.0); 4]
                    };
                }
            }
        });
}

/// `v[r]`, or `v` itself when empty (a per-particle array that is only kept when needed).
fn part(v: &[f64], r: std::ops::Range<usize>) -> &[f64] {
    if v.is_empty() { v } else { &v[r] }
}

/// The engine's arrays, which the simulator keeps from one run to the next so that a run
/// reuses them instead of faulting in fresh pages (tens of MB at 100k particles).
#[derive(Debug)]
pub(crate) struct Buffers<T> {
    /// The state.
    p: Option<Soa<T>>,
    /// The buffer a re-sort or the write-back fills (then swapped with `p`).
    spare: Option<Soa<T>>,
    /// The positions the next substep writes (then swapped with `p.x`).
    x_next: Vec<T>,
    /// The affine matrices `A` (9 fields).
    a: Vec<T>,
    /// Extra momentum of the current substep (3 fields), when forces act.
    extra: Vec<T>,
    /// Per-particle mass, volume, μ, λ in slot order.
    mass: Vec<T>,
    volume: Vec<T>,
    mu: Vec<T>,
    lam: Vec<T>,
    groups: Groups,
    /// `[mv, m]` per node (kg·m/s, kg), zero outside `active`.
    nodes: Vec<[T; 4]>,
    active: NodeBox,
    /// `[v, 0]` per node (m/s).
    vgrid: Vec<[T; 4]>,
}

impl<T> Default for Buffers<T> {
    fn default() -> Self {
        Self {
            p: None,
            spare: None,
            x_next: Vec::new(),
            a: Vec::new(),
            extra: Vec::new(),
            mass: Vec::new(),
            volume: Vec::new(),
            mu: Vec::new(),
            lam: Vec::new(),
            groups: Groups::default(),
            nodes: Vec::new(),
            active: NodeBox::default(),
            vgrid: Vec::new(),
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

/// `src` copied into `v` with the padding of [`padded_array`].
fn fill_padded<T: Real>(v: &mut Vec<T>, src: &[f64], pad: f64) {
    v.clear();
    v.extend(src.iter().map(|&x| T::of(x)));
    v.resize(padded(src.len()), T::of(pad));
}

/// One run of the vectorised engine in precision `T`.
pub(crate) struct Engine<'s, T, M: Constitutive> {
    sim: &'s Simulator<M>,
    /// Position of the grid's first node (m): particle positions are stored relative to it.
    origin: DVec3,
    /// The domain relative to `origin`, rounded inwards (m).
    lo: [T; 3],
    hi: [T; 3],
    /// Slot `i` holds the caller's particle `ids[i]`; particle `p` sits in slot `rank[p]`.
    ids: Vec<u32>,
    rank: Vec<u32>,
    p: Soa<T>,
    b: Buffers<T>,
    /// The caller's material in slot order (`f64`, kept for the per-particle models only).
    mat: Material,
    /// Whether every particle has the same mass, volume, μ and λ.
    uniform: bool,
    /// The caller's forces and impulses, and the same renumbered to slots.
    forces: Vec<ParticleForce>,
    slot_forces: Vec<ParticleForce>,
    /// Groups right after the last sort.
    sorted_groups: usize,
}

impl<'s, T: Precise, M: Constitutive> Engine<'s, T, M> {
    /// The engine loaded with `state` (validated, positions inside the domain) and `mat`,
    /// particles sorted by cell, in the buffers `b` (a previous run's, or empty).
    pub(crate) fn new(
        sim: &'s Simulator<M>,
        state: &State,
        mat: &Material,
        mut b: Buffers<T>,
    ) -> Self {
        let grid = &sim.grid;
        let origin = grid.node_pos([0, 0, 0]);
        let lo_l = grid.domain.lo - origin;
        let hi_l = grid.domain.hi - origin;
        let n = state.len();
        let st = padded(n);
        // In the caller's order first; sorted below.
        let p = Soa::from_state(state, origin, b.p.take());
        b.x_next = scratch(std::mem::take(&mut b.x_next), 3 * st);
        b.a = scratch(std::mem::take(&mut b.a), 9 * st);
        fill_padded(&mut b.mass, &mat.mass, 0.0);
        fill_padded(&mut b.volume, &mat.volume, 0.0);
        fill_padded(&mut b.mu, &mat.mu, 0.0);
        fill_padded(&mut b.lam, &mat.lam, 0.0);
        if b.nodes.len() != grid.len() {
            b.nodes = vec![[T::of(0.0); 4]; grid.len()];
            b.vgrid = vec![[T::of(0.0); 4]; grid.len()];
            b.active = NodeBox::default();
        }
        let same = |v: &[f64]| v.iter().all(|&x| x == v[0]);
        let uniform = [&mat.mass, &mat.volume, &mat.mu, &mat.lam]
            .into_iter()
            .all(|v| same(v))
            && mat.family.is_empty();
        // The per-particle models read the f64 material.
        let keep_mat = M::LANE_KERNEL == LaneKernel::PerParticle || !mat.family.is_empty();
        let mut e = Self {
            sim,
            origin,
            lo: std::array::from_fn(|a| T::of_up(lo_l[a])),
            hi: std::array::from_fn(|a| T::of_down(hi_l[a])),
            ids: (0..n as u32).collect(),
            rank: (0..n as u32).collect(),
            p,
            b,
            mat: if keep_mat {
                mat.clone()
            } else {
                Material {
                    mass: Vec::new(),
                    volume: Vec::new(),
                    mu: Vec::new(),
                    lam: Vec::new(),
                    family: Vec::new(),
                }
            },
            uniform,
            forces: sim.config.forces.clone(),
            slot_forces: sim.config.forces.clone(),
            sorted_groups: 0,
        };
        e.b.groups.rebuild(grid, &e.p);
        e.resort();
        e
    }

    /// The buffers, for the next run.
    pub(crate) fn into_buffers(mut self) -> Buffers<T> {
        self.b.p = Some(self.p);
        self.b
    }

    /// Re-sorts the particles by their current cells (`groups.key`): the state, the
    /// per-particle material, the indices and the forces follow.
    fn resort(&mut self) {
        let Some(rel) = Order::by_key(&self.b.groups.key, self.sim.grid.len()) else {
            return;
        };
        let from = rel.slots();
        let mut next = self.spare();
        self.p.permute_into(from, &mut next);
        self.b.spare = Some(std::mem::replace(&mut self.p, next));
        if !self.uniform {
            let b = &mut self.b;
            for v in [&mut b.mass, &mut b.volume, &mut b.mu, &mut b.lam] {
                let old = v.clone();
                for (d, &i) in v.iter_mut().zip(from) {
                    *d = old[i as usize];
                }
            }
        }
        if !self.mat.mass.is_empty() {
            self.mat = rel.sort_material(&self.mat);
        }
        let order = Order::from_slots(from.iter().map(|&i| self.ids[i as usize]).collect());
        if !self.forces.is_empty() {
            self.slot_forces = order.sort_forces(&self.forces);
        }
        self.rank = order.ranks().to_vec();
        self.ids = order.slots().to_vec();
        self.b.groups.rebuild(&self.sim.grid, &self.p);
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
    pub(crate) fn write_back(&mut self, state: &mut State) {
        let mut out = self.spare();
        self.p.permute_into(&self.rank, &mut out);
        out.to_state(self.origin, state);
        self.b.spare = Some(out);
        let grid = &self.sim.grid;
        state.x.par_iter_mut().for_each(|x| {
            if x.is_finite() {
                grid.hold(x);
            }
        });
    }

    /// Steps 1–4 for every particle: `F` (in place) and `A`; returns whether some new `F` is
    /// NaN/Inf.
    fn stress(&mut self, isa: Isa) -> bool {
        let sim = self.sim;
        let grid = &sim.grid;
        let (n, st) = (self.p.n, self.p.stride);
        let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
        let (head, tail) = self.p.vcf.split_at_mut(F * st);
        let c: [&[T]; 9] = fields(head, st, C);
        let f: [&mut [T]; 9] = fields_mut(tail, st, 0);
        let b = &mut self.b;
        let a: [&mut [T]; 9] = fields_mut(&mut b.a, st, 0);
        let cuts: Vec<usize> = (0..st.div_ceil(STRESS_CHUNK))
            .map(|k| k * STRESS_CHUNK)
            .chain(std::iter::once(st))
            .collect();
        let model = &sim.model;
        let mat = &self.mat;
        let (mass, volume, mu, lam) = (&b.mass, &b.volume, &b.mu, &b.lam);
        let uniform = self.uniform;
        split_fields(f, &cuts)
            .into_par_iter()
            .zip(split_fields(a, &cuts))
            .enumerate()
            .map(|(k, (f, a))| {
                let r = cuts[k]..cuts[k + 1];
                let real = n.saturating_sub(r.start).min(r.len());
                let rr = r.start..r.start + real;
                // The f64 material is kept only for the per-particle models.
                let family = if mat.family.is_empty() {
                    &mat.family[..]
                } else {
                    &mat.family[rr.clone()]
                };
                isa.run_wide(StressTask {
                    model,
                    dt: sim.config.dt,
                    d_inv,
                    real,
                    uniform,
                    c: c.map(|x| &x[r.clone()]),
                    mass: &mass[r.clone()],
                    volume: &volume[r.clone()],
                    mu: &mu[r.clone()],
                    lam: &lam[r.clone()],
                    mu64: part(&mat.mu, rr.clone()),
                    lam64: part(&mat.lam, rr),
                    family,
                    f,
                    a,
                    keep: None,
                })
            })
            .reduce(|| false, |x, y| x | y)
    }

    /// Steps 5–6: P2G of `x, v, A` (and the forces' momentum at time `t`) into the nodes of
    /// the particles' box, then the grid update.
    fn particles_to_grid(&mut self, isa: Isa, t: f64) {
        let sim = self.sim;
        let grid = &sim.grid;
        let (n, st) = (self.p.n, self.p.stride);
        let dt = sim.config.dt;
        let extra = extra_momentum(&self.slot_forces, n, t, dt);
        let b = &mut self.b;
        if let Some(e) = &extra {
            b.extra.clear();
            b.extra.resize(3 * st, T::of(0.0));
            for (i, m) in e.iter().enumerate() {
                for d in 0..3 {
                    b.extra[d * st + i] = T::of(m[d]);
                }
            }
        }
        b.active.fill(grid, &mut b.nodes, [T::of(0.0); 4]);
        b.active = b.groups.touched.clone();
        let x: [&[T]; 3] = fields(&self.p.x, st, 0);
        let v: [&[T]; 3] = fields(&self.p.vcf, st, V);
        let a: [&[T]; 9] = fields(&b.a, st, 0);
        let extra = extra.as_ref().map(|_| fields::<T, 3>(&b.extra, st, 0));
        let mass = &b.mass;
        b.groups
            .scatter(grid, &mut b.nodes, |groups, piece, first| {
                isa.run_wide(P2gTask {
                    grid,
                    groups,
                    x,
                    v,
                    a,
                    mass,
                    extra,
                    piece,
                    first,
                })
            });
        grid_update(
            grid,
            &b.nodes,
            &b.active,
            dt,
            sim.config.gravity,
            &sim.config.boundaries,
            &mut b.vgrid,
        );
    }

    /// Step 7: G2P, `x ← hold(x + dt v)` (into `x_next`, then swapped in); returns the
    /// particles held and whether some new value is NaN/Inf.
    fn g2p(&mut self, isa: Isa) -> (usize, bool) {
        let grid = &self.sim.grid;
        let (n, st) = (self.p.n, self.p.stride);
        let tasks = self.b.groups.tasks(G2P_CHUNK);
        let cuts: Vec<usize> = tasks
            .iter()
            .map(|t| t.1)
            .chain(std::iter::once(n))
            .collect();
        let x_old: [&[T]; 3] = fields(&self.p.x, st, 0);
        let x: [&mut [T]; 3] = fields_mut(&mut self.b.x_next, st, 0);
        let (vc, _) = self.p.vcf.split_at_mut(F * st);
        let vc: [&mut [T]; 12] = fields_mut(vc, st, 0);
        let [v0, v1, v2, c0, c1, c2, c3, c4, c5, c6, c7, c8] = vc;
        let vgrid = bytemuck::cast_slice(&self.b.vgrid);
        let (lo, hi, dt) = (self.lo, self.hi, self.sim.config.dt);
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

    /// One substep at time `t` (s); returns the particles held at the domain edge and whether
    /// some new value is NaN/Inf. `resort`: sort the particles again when their groups have
    /// broken up ([`RESORT_GROWTH`]).
    pub(crate) fn substep(&mut self, t: f64, resort: bool) -> (usize, bool) {
        let isa = Isa::detect();
        self.b.groups.rebuild(&self.sim.grid, &self.p);
        let groups = self.b.groups.list.len();
        if self.sorted_groups == 0 {
            self.sorted_groups = groups;
        } else if resort && groups as f64 > RESORT_GROWTH * self.sorted_groups as f64 {
            self.resort();
            self.sorted_groups = self.b.groups.list.len();
        }
        let bad_f = self.stress(isa);
        self.particles_to_grid(isa, t);
        let (held, bad) = self.g2p(isa);
        (held, bad || bad_f)
    }
}

/// [`Simulator::run`] on the vectorised engine in precision `T`: `state` validated and held in
/// the domain; the report `rep` continues.
pub(crate) fn run<T: Precise, M: Constitutive>(
    sim: &Simulator<M>,
    state: &mut State,
    mat: &Material,
    t0: f64,
    n_substeps: usize,
    rep: &mut RunReport,
) -> Result<(), MpmError> {
    let cached = sim.wide_cache.take::<Buffers<T>>().unwrap_or_default();
    let mut e = Engine::<T, M>::new(sim, state, mat, cached);
    for k in 0..n_substeps {
        let (held, bad) = e.substep(t0 + k as f64 * sim.config.dt, true);
        if bad {
            e.write_back(state);
            let (quantity, particle) = state.first_non_finite().unwrap_or(("x", 0));
            return Err(MpmError::NonFinite {
                substep: k,
                quantity,
                particle,
            });
        }
        rep.substeps += 1;
        rep.held += held;
        rep.max_held = rep.max_held.max(held);
    }
    e.write_back(state);
    sim.wide_cache.put(e.into_buffers());
    Ok(())
}
