//! Checkpointed forward and backward passes on the vectorised engine.
//!
//! The forward pass keeps the state every `every` substeps (a checkpoint). A taped run
//! re-sorts its particles only at checkpoints (when their groups have broken up, as a plain
//! run does at any substep), and each checkpoint keeps its slot order, so a segment's
//! recomputation runs in the forward's order. Until a run first re-sorts, the sums run in one
//! order whatever the checkpoint interval, and the gradients do not depend on it, bit for bit.
//! The backward pass reverses one segment at a time from its checkpoint, recomputing states
//! with at most `snapshots` of them alive (the binomial schedule of
//! `crate::adjoint::schedule`) and keeping the intermediates of recomputed substeps when a
//! segment fits in the snapshots; each reversed substep is the adjoint chain of
//! [`super::adjoint`]. The forward pass keeps the [`Lead`] of the last segment's reversal, which
//! the first backward pass takes instead of recomputing it.

use std::sync::{Arc, Mutex};

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use super::adjoint::{
    G2pAdjTask, ModelAdjGrad, ModelAdjTask, P2gAdjOut, P2gAdjTask, grid_update_adjoint,
};
use super::groups::{Group, task_cuts};
use super::simd::{Precise, Real};
use super::soa::{C, F, Soa, V};
use super::{
    Buffers, Engine, G2P_CHUNK, STRESS_CHUNK, Work, chunk_cuts, fields, fields_mut, split_fields,
};
use crate::adjoint::schedule::{SEGMENT_SNAPSHOTS, Schedule};
use crate::error::MpmError;
use crate::grid::NodeBox;
use crate::isa::Isa;
use crate::models::Constitutive;
use crate::sim::{RunReport, Simulator};
use crate::state::{FamilyGrad, Material, MaterialGrad, State, StateGrad};

/// A state and its slot order (slot `i` holds the caller's particle `ids[i]`; shared by the
/// checkpoints between two re-sorts of a taped run).
#[derive(Debug, Clone)]
pub(crate) struct Checkpoint<T> {
    pub p: Soa<T>,
    pub ids: Arc<[u32]>,
}

impl<T: Real> Checkpoint<T> {
    /// Slot of each of the caller's particles.
    fn rank(&self) -> Vec<u32> {
        let mut r = vec![0u32; self.ids.len()];
        for (i, &p) in self.ids.iter().enumerate() {
            r[p as usize] = i as u32;
        }
        r
    }

    /// The state in the caller's order (positions shifted by `+origin`, m).
    pub fn state(&self, origin: DVec3) -> State {
        let mut s = State::at_rest(vec![DVec3::ZERO; self.p.n]);
        self.p.to_state(&self.rank(), origin, &mut s, false);
        s
    }
}

/// The checkpoints of a forward pass.
#[derive(Debug, Clone)]
pub(crate) struct WideTape<T> {
    /// `checkpoints[j]` = state at substep `j·every`.
    pub checkpoints: Vec<Checkpoint<T>>,
    /// State after the last substep.
    pub last: Checkpoint<T>,
    /// The node the states' positions are measured from, and its position (m).
    pub anchor: glam::IVec3,
    pub origin: DVec3,
    /// What the last segment's reversal starts with, computed as the forward pass ran it.
    pub lead: LeadSlot<T>,
    /// The schedule of a segment at the default [`SEGMENT_SNAPSHOTS`] (tabulating it costs
    /// O(every²), so the backward pass reuses it).
    pub schedule: Arc<Schedule>,
}

impl<T: Real> WideTape<T> {
    /// The checkpoints' state buffers (and the lead's, when no backward pass took it),
    /// leaving the tape empty.
    pub fn take_buffers(&mut self) -> Vec<Soa<T>> {
        let mut out: Vec<Soa<T>> = self.checkpoints.drain(..).map(|c| c.p).collect();
        out.push(std::mem::replace(&mut self.last.p, Soa::empty()));
        out.extend(self.lead.take().states.into_iter().map(|(_, p)| p));
        out
    }
}

/// The start of the last segment's reversal, which the forward pass computes anyway as it runs
/// that segment: the states the backward pass's schedule recomputes first (its outermost chain,
/// [`Schedule::lead`], at the default [`SEGMENT_SNAPSHOTS`]) and, in a short segment, each
/// substep's intermediates. The backward pass looks a state up by its substep (a state of the
/// run is the same whichever state it is recomputed from), so any schedule may use them.
#[derive(Debug)]
pub(crate) struct Lead<T> {
    /// `(k, state at substep k)`.
    states: Vec<(usize, Soa<T>)>,
    /// `(k, intermediates of substep k)`.
    works: Vec<(usize, Work<T>)>,
}

impl<T> Default for Lead<T> {
    fn default() -> Self {
        Self {
            states: Vec::new(),
            works: Vec::new(),
        }
    }
}

impl<T> Lead<T> {
    fn take_state(&mut self, k: usize) -> Option<Soa<T>> {
        let i = self.states.iter().position(|(j, _)| *j == k)?;
        Some(self.states.swap_remove(i).1)
    }

    fn take_work(&mut self, k: usize) -> Option<Work<T>> {
        let i = self.works.iter().position(|(j, _)| *j == k)?;
        Some(self.works.swap_remove(i).1)
    }
}

/// A tape's [`Lead`], taken by the first backward pass through it (its buffers then serve the
/// other segments' recomputation, so the lead adds nothing to the backward pass's peak
/// memory); a cloned tape has none.
#[derive(Debug)]
pub(crate) struct LeadSlot<T>(Mutex<Option<Lead<T>>>);

impl<T> LeadSlot<T> {
    fn new(lead: Lead<T>) -> Self {
        Self(Mutex::new(Some(lead)))
    }

    /// The lead, leaving none (empty when taken before).
    pub fn take(&self) -> Lead<T> {
        self.0
            .lock()
            .ok()
            .and_then(|mut l| l.take())
            .unwrap_or_default()
    }
}

impl<T> Clone for LeadSlot<T> {
    fn clone(&self) -> Self {
        Self(Mutex::new(None))
    }
}

/// First substep of the last segment of `n_substeps` checkpointed every `every`.
fn last_segment_start(n_substeps: usize, every: usize) -> usize {
    n_substeps.saturating_sub(1) / every * every
}

/// A copy of `src` in a buffer of `pool` (a dropped tape's), else in a new one.
fn kept_copy<T: Real>(pool: &mut Vec<Soa<T>>, src: &Soa<T>) -> Soa<T> {
    match pool.pop() {
        Some(mut b) => {
            b.x.copy_from_slice(&src.x);
            b.vcf.copy_from_slice(&src.vcf);
            b
        }
        None => src.clone(),
    }
}

/// Runs `n_substeps` from `state` (validated and held; advanced in place), keeping a
/// checkpoint every `every` (in the buffers of the simulator's last dropped tape when there
/// are any); the report `rep` continues.
pub(crate) fn forward_tape<T: Precise, M: Constitutive>(
    sim: &Simulator<M>,
    state: &mut State,
    mat: &Material,
    t0: f64,
    n_substeps: usize,
    every: usize,
    rep: &mut RunReport,
) -> Result<WideTape<T>, MpmError> {
    let cached = sim.wide_cache.take::<Buffers<T>>().unwrap_or_default();
    let mut e = Engine::<T, M>::new(sim, state, mat, cached);
    let mut pool: Vec<Soa<T>> = sim.tape_pool.0.take::<Vec<Soa<T>>>().unwrap_or_default();
    pool.retain(|b| b.n == e.p.n && b.stride == e.p.stride);
    let mut checkpoints = Vec::with_capacity(n_substeps.div_ceil(every));
    // The last segment's lead, in buffers the last backward pass released.
    let last_lo = last_segment_start(n_substeps, every);
    let schedule = Arc::new(Schedule::new(
        every.min(n_substeps.max(1)),
        SEGMENT_SNAPSHOTS,
    ));
    let (lead_states, lead_works) = schedule.lead(last_lo, n_substeps, SEGMENT_SNAPSHOTS);
    let mut back = sim.adjoint_cache.take::<BackCache<T>>();
    let (mut spare_soas, mut spare_works) = match back.as_mut() {
        Some(b) => (std::mem::take(&mut b.soas), std::mem::take(&mut b.works)),
        None => (Vec::new(), Vec::new()),
    };
    spare_soas.retain(|b| b.n == e.p.n && b.stride == e.p.stride);
    let mut lead = Lead::default();
    // The slot order, shared by the checkpoints between re-sorts.
    let mut ids: Arc<[u32]> = e.ids.as_slice().into();
    for k in 0..n_substeps {
        let at_checkpoint = k.is_multiple_of(every);
        if let Err(err) = e.regroup(at_checkpoint) {
            e.write_back(state);
            give_back(sim, back, spare_soas, spare_works);
            return Err(err.at_substep(k));
        }
        if at_checkpoint {
            if *ids != *e.ids {
                ids = e.ids.as_slice().into();
            }
            checkpoints.push(Checkpoint {
                p: kept_copy(&mut pool, &e.p),
                ids: Arc::clone(&ids),
            });
        }
        // Keeping a substep's intermediates changes none of its arithmetic.
        e.keep = lead_works.contains(&k);
        if e.keep {
            e.b.work.fit(e.p.n, true, Engine::<T, M>::KEEP_TAU);
        }
        let outcome = e.step(t0 + k as f64 * sim.config.dt);
        if let Err(err) = e.record(k, outcome, rep) {
            e.write_back(state);
            give_back(sim, back, spare_soas, spare_works);
            return Err(err);
        }
        if e.keep {
            let spare = spare_works.pop().unwrap_or_default();
            lead.works.push((k, e.take_work(spare)));
        }
        if lead_states.contains(&(k + 1)) {
            let from = if spare_soas.is_empty() {
                &mut pool
            } else {
                &mut spare_soas
            };
            lead.states.push((k + 1, kept_copy(from, &e.p)));
        }
    }
    e.keep = false;
    give_back(sim, back, spare_soas, spare_works);
    let last = Checkpoint {
        p: kept_copy(&mut pool, &e.p),
        ids,
    };
    drop(pool);
    let (anchor, origin) = (e.anchor, e.origin);
    e.write_back(state);
    sim.wide_cache.put(e.into_buffers());
    Ok(WideTape {
        checkpoints,
        last,
        anchor,
        origin,
        lead: LeadSlot::new(lead),
        schedule,
    })
}

/// Returns the spare buffers a forward pass did not use to the backward pass's cache `back`
/// (taken from `sim`).
fn give_back<T: Real, M: Constitutive>(
    sim: &Simulator<M>,
    back: Option<BackCache<T>>,
    soas: Vec<Soa<T>>,
    works: Vec<Work<T>>,
) {
    if let Some(mut b) = back {
        (b.soas, b.works) = (soas, works);
        sim.adjoint_cache.put(b);
    }
}

/// The backward pass's arrays, kept by the simulator between passes (as [`Buffers`] for
/// runs): the engine's, the adjoint kernels', and released snapshots and intermediates.
#[derive(Debug)]
pub(crate) struct BackCache<T> {
    engine: Buffers<T>,
    adj: AdjBuffers<T>,
    soas: Vec<Soa<T>>,
    works: Vec<Work<T>>,
    /// The running state gradient and the material accumulators.
    grad: Option<Soa<T>>,
    acc: Option<MatAcc>,
}

impl<T> Default for BackCache<T> {
    fn default() -> Self {
        Self {
            engine: Buffers::default(),
            adj: AdjBuffers::default(),
            soas: Vec::new(),
            works: Vec::new(),
            grad: None,
            acc: None,
        }
    }
}

/// Scratch of the adjoint kernels.
#[derive(Debug)]
pub(crate) struct AdjBuffers<T> {
    /// The layout of the node arrays.
    grid: crate::grid::GridSpec,
    /// `[v̄, 0]` per node, zero outside `g_active`.
    gvgrid: Vec<[T; 4]>,
    g_active: NodeBox,
    /// `[m̄v, m̄]` per node.
    gnodes: Vec<[T; 4]>,
    /// `x̄` of each group from the G2P adjoint, in slab order.
    gx_groups: Vec<[[T; 8]; 3]>,
    /// `Ā` (9 fields) and `Σ w m̄_i` (1) from the P2G adjoint.
    abar: Vec<T>,
    sm: Vec<T>,
}

impl<T> Default for AdjBuffers<T> {
    fn default() -> Self {
        Self {
            grid: crate::grid::GridSpec::empty(),
            gvgrid: Vec::new(),
            g_active: NodeBox::default(),
            gnodes: Vec::new(),
            gx_groups: Vec::new(),
            abar: Vec::new(),
            sm: Vec::new(),
        }
    }
}

/// Material gradients in slot order (`f64`, padded like the state).
#[derive(Debug, Clone)]
pub(crate) struct MatAcc {
    pub mass: Vec<f64>,
    pub volume: Vec<f64>,
    pub mu: Vec<f64>,
    pub lam: Vec<f64>,
    /// Per particle (empty unless the model has family scalars).
    pub family: Vec<FamilyGrad>,
}

impl MatAcc {
    /// `old` zeroed when it has this shape, else new zeros.
    pub fn zeroed(old: Option<Self>, stride: usize, family: bool) -> Self {
        match old {
            Some(mut a) if a.mass.len() == stride && a.family.is_empty() != family => {
                for v in [&mut a.mass, &mut a.volume, &mut a.mu, &mut a.lam] {
                    v.fill(0.0);
                }
                a.family.fill(FamilyGrad::default());
                a
            }
            _ => Self::zeros(stride, family),
        }
    }

    pub fn zeros(stride: usize, family: bool) -> Self {
        Self {
            mass: vec![0.0; stride],
            volume: vec![0.0; stride],
            mu: vec![0.0; stride],
            lam: vec![0.0; stride],
            family: if family {
                vec![FamilyGrad::default(); stride]
            } else {
                Vec::new()
            },
        }
    }

    /// Adds the slot-order gradients (slot `i` = the caller's `ids[i]`) into `g`.
    pub fn add_into(&self, ids: &[u32], g: &mut MaterialGrad) {
        for (i, &p) in ids.iter().enumerate() {
            let p = p as usize;
            g.mass[p] += self.mass[i];
            g.volume[p] += self.volume[i];
            g.mu[p] += self.mu[i];
            g.lam[p] += self.lam[i];
        }
        if !self.family.is_empty() {
            g.family_per_particle
                .resize(ids.len(), FamilyGrad::default());
            for (i, &p) in ids.iter().enumerate() {
                g.family = g.family + self.family[i];
                let q = &mut g.family_per_particle[p as usize];
                *q = *q + self.family[i];
            }
        }
    }
}

/// The adjoint of the substep whose start state is `s` and intermediates `work` (slot order
/// of the engine): `g` holds `∂L/∂s_{k+1}` on entry and `∂L/∂s_k` on return, the material
/// gradients are added to `acc`. Returns whether some new gradient is NaN/Inf.
pub(crate) fn adjoint_step<T: Precise, M: Constitutive>(
    e: &Engine<'_, T, M>,
    s: &Soa<T>,
    work: &Work<T>,
    g: &mut Soa<T>,
    acc: &mut MatAcc,
    adj: &mut AdjBuffers<T>,
) -> bool {
    let sim = e.sim;
    let grid = &work.grid;
    let dt = sim.config.dt;
    let isa = Isa::detect();
    let (n, st) = (s.n, s.stride);
    let groups = &work.groups;
    // G2P: node gradients v̄_i (scattered) and each group's x̄.
    super::relayout(&mut adj.gvgrid, &mut adj.g_active, &adj.grid, grid);
    adj.grid = *grid;
    adj.g_active.fill(grid, &mut adj.gvgrid, [T::of(0.0); 4]);
    adj.g_active = work.active.clone();
    let v_max = work.v_max;
    let scale = (grid.dims.iter().copied().max().unwrap_or(1) as f64) * grid.dx;
    // f32 positions: the margin test must also cover the rounding of x + dt v.
    let eps = if T::N == 8 { 1e-6 } else { 1e-12 };
    let reach = T::of(dt * v_max * (1.0 + 1e-6) + eps * (1.0 + scale));
    adj.gx_groups
        .resize(groups.by_slab.len(), [[T::of(0.0); 8]; 3]);
    {
        let x: [&[T]; 3] = fields(&s.x, st, 0);
        let gx: [&[T]; 3] = fields(&g.x, st, 0);
        let gv: [&[T]; 3] = fields(&g.vcf, st, V);
        let gc: [&[T]; 9] = fields(&g.vcf, st, C);
        let vgrid = bytemuck::cast_slice(&work.vgrid);
        let (lo, hi) = (e.lo, e.hi);
        groups.scatter_with(
            grid,
            &mut adj.gvgrid,
            &mut adj.gx_groups,
            |gs, out_x, piece, first| {
                isa.run_wide(G2pAdjTask {
                    grid,
                    groups: gs,
                    x,
                    gx,
                    gv,
                    gc,
                    vgrid,
                    dt,
                    lo,
                    hi,
                    reach,
                    piece,
                    first,
                    out_x,
                })
            },
        );
    }
    for (gr, out) in groups.by_slab.iter().zip(&adj.gx_groups) {
        let (s0, m) = (gr.start as usize, gr.n as usize);
        for (a, o) in out.iter().enumerate() {
            g.x[a * st + s0..a * st + s0 + m].copy_from_slice(&o[..m]);
        }
    }
    // The grid update.
    grid_update_adjoint(
        grid,
        &work.nodes,
        &adj.gvgrid,
        &work.active,
        dt,
        sim.config.gravity,
        &sim.config.boundaries,
        &mut adj.gnodes,
    );
    // P2G (a gather per group): x̄ += …, ḡ into v̄'s place, Ā, Σ w m̄_i.
    if adj.abar.len() != 9 * st {
        adj.abar = vec![T::of(0.0); 9 * st];
        adj.sm = vec![T::of(0.0); st];
    }
    let mat = e.material();
    {
        let tasks = groups.tasks(G2P_CHUNK);
        let cuts = task_cuts(&tasks, n);
        let x: [&[T]; 3] = fields(&s.x, st, 0);
        let v: [&[T]; 3] = fields(&s.vcf, st, V);
        let a: [&[T]; 9] = fields(&work.a, st, 0);
        let extra = work.extra.as_ref().map(|x| fields::<T, 3>(x, st, 0));
        let gnodes = bytemuck::cast_slice(&adj.gnodes);
        let gx: [&mut [T]; 3] = fields_mut(&mut g.x, st, 0);
        let gv: [&mut [T]; 3] = fields_mut(&mut g.vcf, st, V);
        let abar: [&mut [T]; 9] = fields_mut(&mut adj.abar, st, 0);
        let [sm]: [&mut [T]; 1] = fields_mut(&mut adj.sm, st, 0);
        split_fields(gx, &cuts)
            .into_par_iter()
            .zip(split_fields(gv, &cuts))
            .zip(split_fields(abar, &cuts))
            .zip(split_fields([sm], &cuts))
            .zip(tasks)
            .for_each(|((((gx, sg), abar), [sm]), (gs, s0, _))| {
                isa.run_wide(P2gAdjTask {
                    grid,
                    groups: gs,
                    s0,
                    x,
                    v,
                    a,
                    mass: mat.mass,
                    uniform_mass: mat.uniform,
                    extra,
                    gnodes,
                    out: P2gAdjOut { gx, sg, abar, sm },
                })
            });
    }
    // Per particle: v̄, C̄, τ̄, m̄, V̄ and the model's adjoint, in full vectors.
    let cuts = chunk_cuts(st, STRESS_CHUNK);
    let d_inv = 4.0 * grid.inv_dx * grid.inv_dx;
    let v: [&[T]; 3] = fields(&s.vcf, st, V);
    let c: [&[T]; 9] = fields(&s.vcf, st, C);
    let f: [&[T]; 9] = fields(&s.vcf, st, F);
    // τ is kept for the per-particle models only (the lane models' adjoints recompute it).
    let tau: [&[T]; 9] = if work.tau.is_empty() {
        [&[]; 9]
    } else {
        fields(&work.tau, st, 0)
    };
    let abar: [&[T]; 9] = fields(&adj.abar, st, 0);
    let (gv, rest) = g.vcf.split_at_mut(C * st);
    let (gc, gf) = rest.split_at_mut(9 * st);
    let gv: [&mut [T]; 3] = fields_mut(gv, st, 0);
    let gc: [&mut [T]; 9] = fields_mut(gc, st, 0);
    let gf: [&mut [T]; 9] = fields_mut(gf, st, 0);
    let fam = M::HAS_FAMILY_PARAMS;
    let gfamily: Vec<&mut [FamilyGrad]> = if fam {
        acc.family.chunks_mut(STRESS_CHUNK).collect()
    } else {
        (0..cuts.len() - 1)
            .map(|_| <&mut [FamilyGrad]>::default())
            .collect()
    };
    split_fields(gv, &cuts)
        .into_par_iter()
        .zip(split_fields(gc, &cuts))
        .zip(split_fields(gf, &cuts))
        .zip(acc.mass.par_chunks_mut(STRESS_CHUNK))
        .zip(acc.volume.par_chunks_mut(STRESS_CHUNK))
        .zip(acc.mu.par_chunks_mut(STRESS_CHUNK))
        .zip(acc.lam.par_chunks_mut(STRESS_CHUNK))
        .zip(gfamily)
        .enumerate()
        .map(
            |(k, (((((((gv, gc), gf), gmass), gvolume), gmu), glam), gfamily))| {
                let r = cuts[k]..cuts[k + 1];
                let real = n.saturating_sub(r.start).min(r.len());
                isa.run_wide(ModelAdjTask {
                    model: &sim.model,
                    dt,
                    d_inv,
                    real,
                    v: v.map(|x| &x[r.clone()]),
                    c: c.map(|x| &x[r.clone()]),
                    f: f.map(|x| &x[r.clone()]),
                    tau: tau.map(|x| if x.is_empty() { x } else { &x[r.clone()] }),
                    aux: &work.aux[r.clone()],
                    abar: abar.map(|x| &x[r.clone()]),
                    sm: &adj.sm[r.clone()],
                    mat: mat.slots(r.clone(), real),
                    g: ModelAdjGrad {
                        gv,
                        gc,
                        gf,
                        gmass,
                        gvolume,
                        gmu,
                        glam,
                        gfamily,
                    },
                })
            },
        )
        .reduce(|| false, |x, y| x | y)
}

/// The state view a seed reads: slot order `ids`, positions relative to `origin`.
pub(crate) struct SlotState<'a, T> {
    pub p: &'a Soa<T>,
    pub ids: &'a [u32],
    pub origin: DVec3,
}

impl<T: Real> crate::adjoint::SeedSource for SlotState<'_, T> {
    fn state(&self) -> State {
        Checkpoint {
            p: self.p.clone(),
            ids: self.ids.into(),
        }
        .state(self.origin)
    }
}

/// The running gradient a seed adds into: slot order, the caller's particle `p` in slot
/// `rank[p]`.
pub(crate) struct SlotGrad<'a, T> {
    pub g: &'a mut Soa<T>,
    pub rank: &'a [u32],
}

impl<T: Real> SlotGrad<'_, T> {
    fn add(&mut self, p: usize, field: usize, v: f64, x: bool) {
        let st = self.g.stride;
        let i = self.rank[p] as usize;
        let a = if x { &mut self.g.x } else { &mut self.g.vcf };
        let e = &mut a[field * st + i];
        *e = *e + T::of(v);
    }

    fn add_mat(&mut self, p: usize, field: usize, m: &DMat3) {
        let rows = crate::math::to_rows(m);
        for (k, r) in rows.iter().flatten().enumerate() {
            self.add(p, field + k, *r, false);
        }
    }
}

impl<T: Real> crate::adjoint::GradSink for SlotGrad<'_, T> {
    fn len(&self) -> usize {
        self.rank.len()
    }
    fn add_x(&mut self, p: usize, g: DVec3) {
        for a in 0..3 {
            self.add(p, a, g[a], true);
        }
    }
    fn add_v(&mut self, p: usize, g: DVec3) {
        for a in 0..3 {
            self.add(p, V + a, g[a], false);
        }
    }
    fn add_c(&mut self, p: usize, g: DMat3) {
        self.add_mat(p, C, &g);
    }
    fn add_f(&mut self, p: usize, g: DMat3) {
        self.add_mat(p, F, &g);
    }
}

/// A gradient state in slot order (`ids`) as the caller's [`StateGrad`]: reordered field by
/// field into `scratch` (a state buffer of the same size, else new), then converted in order.
pub(crate) fn to_state_grad<T: Real>(
    g: &Soa<T>,
    ids: &[u32],
    scratch: Option<Soa<T>>,
    mut out: StateGrad,
) -> (StateGrad, Soa<T>) {
    let n = ids.len();
    let mut rank = vec![0u32; n];
    for (i, &p) in ids.iter().enumerate() {
        rank[p as usize] = i as u32;
    }
    let mut c = scratch
        .filter(|s| s.n == n)
        .unwrap_or_else(|| Soa::zeros(n));
    g.permute_into(&rank, &mut c);
    let st = c.stride;
    let at = |f: &[T], field: usize, i: usize| f[field * st + i].f64();
    let (x, vcf) = (&c.x, &c.vcf);
    // Into `out`'s arrays (kept when they already hold `n`).
    let vec3 = |out: &mut Vec<DVec3>, f: &[T], base: usize| {
        out.resize(n, DVec3::ZERO);
        out.par_iter_mut().enumerate().for_each(|(i, o)| {
            *o = DVec3::new(at(f, base, i), at(f, base + 1, i), at(f, base + 2, i));
        });
    };
    // Row-major fields into column-major matrices.
    let mat3 = |out: &mut Vec<DMat3>, base: usize| {
        out.resize(n, DMat3::ZERO);
        out.par_iter_mut().enumerate().for_each(|(i, o)| {
            *o = DMat3::from_cols_array(&std::array::from_fn(|k| {
                at(vcf, base + 3 * (k % 3) + k / 3, i)
            }));
        });
    };
    vec3(&mut out.x, x, 0);
    vec3(&mut out.v, vcf, V);
    mat3(&mut out.c, C);
    mat3(&mut out.f, F);
    (out, c)
}

/// The first NaN/Inf of a gradient state (slot order `ids`), as (quantity, caller's index).
fn first_non_finite<T: Real>(g: &Soa<T>, ids: &[u32]) -> Option<(&'static str, usize)> {
    to_state_grad(g, ids, None, StateGrad::default())
        .0
        .first_non_finite()
}

/// `g` (slot order `from_ids`) reordered to slot order `to_ids`, written into `scratch` (a
/// state buffer of the same size, else new; padding set to 0).
fn reorder<T: Real>(
    g: &Soa<T>,
    from_ids: &[u32],
    to_ids: &[u32],
    scratch: Option<Soa<T>>,
) -> Soa<T> {
    let mut rank = vec![0u32; from_ids.len()];
    for (i, &p) in from_ids.iter().enumerate() {
        rank[p as usize] = i as u32;
    }
    let from: Vec<u32> = to_ids.iter().map(|&p| rank[p as usize]).collect();
    let mut out = match scratch.filter(|s| s.n == g.n) {
        Some(mut s) => {
            let (n, st) = (s.n, s.stride);
            for f in s.x.chunks_exact_mut(st).chain(s.vcf.chunks_exact_mut(st)) {
                f[n..].fill(T::of(0.0));
            }
            s
        }
        None => Soa::zeros(g.n),
    };
    g.permute_into(&from, &mut out);
    out
}

/// A seed: adds `∂L/∂state_k` at substep `k` given the state.
pub(crate) type SeedFn<'a> = dyn FnMut(
        usize,
        &dyn crate::adjoint::SeedSource,
        &mut dyn crate::adjoint::GradSink,
    ) -> Result<(), MpmError>
    + 'a;

/// Backpropagates through `tape` (substeps `t0 + k dt`, `k < n_substeps`, checkpoints every
/// `every`); `start` = first substep reversed. Returns `∂L/∂state_start` (caller's order) and
/// the material gradients.
#[allow(clippy::too_many_arguments)]
pub(crate) fn backward<T: Precise, M: Constitutive>(
    sim: &Simulator<M>,
    tape: &WideTape<T>,
    mat: &Material,
    t0: f64,
    n_substeps: usize,
    every: usize,
    start: usize,
    snapshots: usize,
    seed: &mut SeedFn<'_>,
    reuse: Option<crate::adjoint::GradArrays>,
) -> Result<(StateGrad, MaterialGrad), MpmError> {
    let np = mat.len();
    // The backward pass's arrays from the last one, else the forward runs' (one set alive).
    let mut cache = sim
        .adjoint_cache
        .take::<BackCache<T>>()
        .unwrap_or_else(|| BackCache {
            engine: sim.wide_cache.take::<Buffers<T>>().unwrap_or_default(),
            ..BackCache::default()
        });
    // A backward pass neither re-sorts nor writes back: no spare state.
    cache.engine.spare = None;
    let p = Engine::<T, M>::soa_from(&mut cache.engine, &tape.last.p);
    let mut e = Engine::<T, M>::with_state(
        sim,
        tape.anchor,
        p,
        tape.last.ids.to_vec(),
        mat,
        std::mem::take(&mut cache.engine),
    );
    e.keep = true;
    let mut g = match cache.grad.take().filter(|g| g.n == np) {
        Some(mut g) => {
            g.x.fill(T::of(0.0));
            g.vcf.fill(T::of(0.0));
            g
        }
        None => Soa::<T>::zeros(np),
    };
    let mut order_g = tape.last.ids.to_vec();
    {
        let rank = tape.last.rank();
        let view = SlotState {
            p: &tape.last.p,
            ids: &tape.last.ids,
            origin: tape.origin,
        };
        seed(
            n_substeps,
            &view,
            &mut SlotGrad {
                g: &mut g,
                rank: &rank,
            },
        )?;
    }
    let (out, mut gmat) = reuse.unwrap_or_default();
    gmat.reset(np);
    // One slot-order accumulator per slot order (a taped run changes it only where it
    // re-sorts), so until then each particle's material gradient sums its substeps in one
    // sequence whatever the checkpoint interval.
    let mut acc = MatAcc::zeroed(cache.acc.take(), tape.last.p.stride, M::HAS_FAMILY_PARAMS);
    let mut acc_ids = tape.last.ids.to_vec();
    let plan = if snapshots == SEGMENT_SNAPSHOTS {
        Arc::clone(&tape.schedule)
    } else {
        Arc::new(Schedule::new(every.min(n_substeps.max(1)), snapshots))
    };
    let mut adj = std::mem::take(&mut cache.adj);
    let mut rev = Reverser {
        t0,
        dt: sim.config.dt,
        start,
        snapshots,
        plan: &plan,
        stack: Vec::new(),
        spare: std::mem::take(&mut cache.soas)
            .into_iter()
            .filter(|s| s.n == np)
            .collect(),
        spare_work: std::mem::take(&mut cache.works),
        keep: false,
        lead: tape.lead.take(),
    };
    // The lead follows the default schedule of a whole pass; another schedule would find few
    // of its states and hold them besides its own (its buffers still serve as snapshots).
    let last_lo = last_segment_start(n_substeps, every);
    if snapshots != SEGMENT_SNAPSHOTS || start > last_lo {
        let lead = std::mem::take(&mut rev.lead);
        let room = snapshots.saturating_sub(rev.spare.len());
        rev.spare
            .extend(lead.states.into_iter().take(room).map(|(_, p)| p));
    }
    for (j, ck) in tape.checkpoints.iter().enumerate().rev() {
        let lo = j * every;
        let hi = (lo + every).min(n_substeps);
        if hi <= start {
            break;
        }
        if *ck.ids != *order_g {
            let next = reorder(&g, &order_g, &ck.ids, rev.spare.pop());
            rev.spare.push(std::mem::replace(&mut g, next));
            order_g = ck.ids.to_vec();
        }
        e.load(ck.p.n, &ck.ids);
        let rank = ck.rank();
        if *acc_ids != *ck.ids {
            acc.add_into(&acc_ids, &mut gmat);
            acc = MatAcc::zeroed(Some(acc), ck.p.stride, M::HAS_FAMILY_PARAMS);
            acc_ids = ck.ids.to_vec();
        }
        let mut ctx = Ctx {
            e: &mut e,
            ck,
            rank: &rank,
            origin: tape.origin,
            g: &mut g,
            acc: &mut acc,
            adj: &mut adj,
            seed: &mut *seed,
        };
        rev.segment(&mut ctx, lo, hi)?;
    }
    acc.add_into(&acc_ids, &mut gmat);
    // What a truncated pass did not use of the lead.
    let lead = std::mem::take(&mut rev.lead);
    rev.spare.extend(lead.states.into_iter().map(|(_, p)| p));
    rev.spare_work
        .extend(lead.works.into_iter().map(|(_, w)| w));
    if M::HAS_FAMILY_PARAMS && gmat.family_per_particle.is_empty() {
        gmat.family_per_particle = vec![FamilyGrad::default(); np];
    }
    let (out, scratch) = to_state_grad(&g, &order_g, rev.spare.pop(), out);
    rev.spare.push(scratch);
    sim.adjoint_cache.put(BackCache {
        engine: e.into_buffers(),
        adj,
        soas: rev.spare,
        works: rev.spare_work,
        grad: Some(g),
        acc: Some(acc),
    });
    Ok((out, gmat))
}

/// What a reversed substep works on.
struct Ctx<'c, 'e, 's, T, M: Constitutive> {
    e: &'c mut Engine<'e, T, M>,
    ck: &'c Checkpoint<T>,
    rank: &'c [u32],
    origin: DVec3,
    g: &'c mut Soa<T>,
    acc: &'c mut MatAcc,
    adj: &'c mut AdjBuffers<T>,
    seed: &'c mut SeedFn<'s>,
}

/// The recomputation schedule of one backward pass (the binomial checkpointing of
/// `crate::adjoint::schedule`).
struct Reverser<'p, T> {
    t0: f64,
    dt: f64,
    start: usize,
    snapshots: usize,
    plan: &'p Schedule,
    /// Recomputed states, innermost last, and released buffers.
    stack: Vec<Soa<T>>,
    spare: Vec<Soa<T>>,
    spare_work: Vec<Work<T>>,
    /// Keep each recomputed substep's intermediates (segments of ≤ snapshots + 1).
    keep: bool,
    /// The forward pass's start of the last segment's reversal: states and intermediates
    /// taken instead of recomputed.
    lead: Lead<T>,
}

impl<T: Precise> Reverser<'_, T> {
    /// Reverses substeps `lo..hi` (only those `≥ start`) from the checkpoint at `lo`.
    fn segment<M: Constitutive>(
        &mut self,
        c: &mut Ctx<'_, '_, '_, T, M>,
        lo: usize,
        hi: usize,
    ) -> Result<(), MpmError> {
        debug_assert!(self.stack.is_empty());
        let a = lo.max(self.start);
        let free = if lo < a {
            self.snapshots.max(2) - 1
        } else {
            self.snapshots
        };
        self.keep = hi - a <= free + 1;
        if lo < a {
            // Truncated: first recompute the state at `start` (one extra snapshot).
            self.push(c, lo, a, false)?;
            let r = self.reverse(c, a, hi, free);
            self.pop();
            return r;
        }
        self.reverse(c, a, hi, free)
    }

    /// Recomputes the state at `to` from the base (at `from`) into a new snapshot; with
    /// `keep`, returns the intermediates of substep `from` (when `to = from + 1`).
    fn push<M: Constitutive>(
        &mut self,
        c: &mut Ctx<'_, '_, '_, T, M>,
        from: usize,
        to: usize,
        keep: bool,
    ) -> Result<Option<Work<T>>, MpmError> {
        if let Some(p) = self.lead.take_state(to) {
            let work = if keep {
                self.lead.take_work(from)
            } else {
                None
            };
            if work.is_some() || !keep {
                self.stack.push(p);
                return Ok(work);
            }
            self.spare.push(p);
        }
        let base = self.stack.last().unwrap_or(&c.ck.p);
        // The first substep reads the base and writes every field of the new buffer (no copy).
        let mut buf = self.spare.pop().unwrap_or_else(|| Soa::new(base.n));
        std::mem::swap(&mut c.e.p, &mut buf);
        let was = c.e.keep;
        c.e.keep = keep;
        // The windows of a following grid are those of the forward pass (same positions).
        let mut r =
            c.e.regroup_from(Some(base), false)
                .map_err(|e| e.at_substep(from));
        if r.is_ok() {
            c.e.step_from(self.t0 + from as f64 * self.dt, Some(base));
            for k in from + 1..to {
                r = c.e.regroup(false).map_err(|e| e.at_substep(k));
                if r.is_err() {
                    break;
                }
                c.e.step(self.t0 + k as f64 * self.dt);
            }
        }
        c.e.keep = was;
        std::mem::swap(&mut c.e.p, &mut buf);
        self.stack.push(buf);
        r?;
        Ok(keep.then(|| {
            let spare = self.spare_work.pop().unwrap_or_default();
            c.e.take_work(spare)
        }))
    }

    fn pop(&mut self) {
        if let Some(s) = self.stack.pop() {
            self.spare.push(s);
        }
    }

    /// Reverses substeps `a..b` whose start state is the base, with `free ≥ 1` snapshots left.
    fn reverse<M: Constitutive>(
        &mut self,
        c: &mut Ctx<'_, '_, '_, T, M>,
        a: usize,
        b: usize,
        free: usize,
    ) -> Result<(), MpmError> {
        let keep = self.keep;
        let mut b = b;
        let mut kept = None;
        while b - a > 1 {
            let m = a + self.plan.split(b - a, free);
            kept = self.push(c, a, m, keep && m == a + 1)?;
            let r = self.reverse(c, m, b, free - 1);
            self.pop();
            r?;
            b = m;
        }
        let r = self.step(c, a, kept.as_ref());
        self.spare_work.extend(kept);
        r
    }

    /// Backpropagates substep `k` from its start state (the base), given its intermediates
    /// when kept, then adds the seed at `k`.
    fn step<M: Constitutive>(
        &mut self,
        c: &mut Ctx<'_, '_, '_, T, M>,
        k: usize,
        kept: Option<&Work<T>>,
    ) -> Result<(), MpmError> {
        let t = self.t0 + k as f64 * self.dt;
        let s = self.stack.last().unwrap_or(&c.ck.p);
        let lead = kept.is_none().then(|| self.lead.take_work(k)).flatten();
        let work = match kept.or(lead.as_ref()) {
            Some(w) => w,
            None => {
                // Recompute the substep's intermediates from `s` (the new F goes to the
                // engine's scratch state).
                c.e.regroup_from(Some(s), false)
                    .map_err(|e| e.at_substep(k))?;
                c.e.grid_from(t, Some(s));
                c.e.work()
            }
        };
        let bad = adjoint_step(c.e, s, work, c.g, c.acc, c.adj);
        self.spare_work.extend(lead);
        if bad && let Some((quantity, particle)) = first_non_finite(c.g, &c.ck.ids) {
            return Err(MpmError::NonFinite {
                substep: k,
                quantity,
                particle,
            });
        }
        let view = SlotState {
            p: s,
            ids: &c.ck.ids,
            origin: c.origin,
        };
        (c.seed)(
            k,
            &view,
            &mut SlotGrad {
                g: c.g,
                rank: c.rank,
            },
        )
    }
}

/// Particles of `groups` as a slot range.
#[allow(dead_code)]
fn slots(g: &Group) -> std::ops::Range<usize> {
    g.start as usize..(g.start + g.n) as usize
}
