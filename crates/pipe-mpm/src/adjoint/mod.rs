//! Reverse mode by hand: one adjoint per kernel, chained backwards through a substep, plus
//! checkpointed multi-substep backpropagation ([`Tape`]).

mod checkpoint;
mod g2p;
mod grid_update;
mod p2g;
mod schedule;

pub use checkpoint::{BackwardOptions, Gradients, SeedGrad, SeedState, Tape};
pub use schedule::SEGMENT_SNAPSHOTS;

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::error::MpmError;
use crate::grid::{NodeBox, Stencil};
use crate::grid_update::NodeVel;
use crate::isa::{Isa, Lanes, WithLanes, any_non_finite};
use crate::models::Constitutive;
use crate::p2g::Node;
use crate::scatter::scatter_with_slabs;
use crate::sim::{Simulator, Work, chunks_or_empty};
use crate::state::{FamilyGrad, Material, MaterialGrad, State, StateGrad};

/// The z-weights of a particle's stencil rows used by both adjoint kernels, as splat vectors:
/// `w_k`, `w_k pz_k`, `w'_k`, `w'_k pz_k` for the row's nodes `k` (`w'` = d w / d fx).
pub(crate) struct ZWeights<L: Lanes> {
    w: [L::V; 3],
    wp: [L::V; 3],
    dw: [L::V; 3],
    dwp: [L::V; 3],
}

impl<L: Lanes> ZWeights<L> {
    /// The z-weights of stencil `st` with node offsets `p` (m).
    #[inline(always)]
    pub(crate) fn new(l: L, st: &Stencil, p: &[DVec3; 3]) -> Self {
        Self {
            w: std::array::from_fn(|k| l.splat(st.w[k].z)),
            wp: std::array::from_fn(|k| l.splat(st.w[k].z * p[k].z)),
            dw: std::array::from_fn(|k| l.splat(st.dw[k].z)),
            dwp: std::array::from_fn(|k| l.splat(st.dw[k].z * p[k].z)),
        }
    }

    /// `Σ_k (w_k, w_k pz_k, w'_k, w'_k pz_k) n_k` over a row's three nodes `n`.
    #[inline(always)]
    pub(crate) fn row_sums(&self, l: L, n: [L::V; 3]) -> [L::V; 4] {
        let zero = l.splat(0.0);
        let mut out = [zero; 4];
        for (k, nk) in n.into_iter().enumerate() {
            out[0] = l.fma(nk, self.w[k], out[0]);
            out[1] = l.fma(nk, self.wp[k], out[1]);
            out[2] = l.fma(nk, self.dw[k], out[2]);
            out[3] = l.fma(nk, self.dwp[k], out[3]);
        }
        out
    }
}

/// Particles per parallel task of the per-particle adjoint pass.
const PARTICLE_CHUNK: usize = 512;

/// Mutable per-particle gradients of one chunk: state `(x̄, v̄, C̄, F̄)`, material
/// `(m̄, V̄, μ̄, λ̄)` and family.
type GradChunk<'a> = (
    &'a mut [DVec3],
    &'a mut [DVec3],
    &'a mut [DMat3],
    &'a mut [DMat3],
    &'a mut [f64],
    &'a mut [f64],
    &'a mut [f64],
    &'a mut [f64],
    &'a mut [FamilyGrad],
);

/// The P2G, constitutive and strain-prediction adjoints of a chunk of particles (starting at
/// particle `first`), as one unit of work for [`Isa::run_lanes`]; returns whether some new
/// state gradient is NaN/Inf.
struct ParticleAdjoint<'a, M> {
    model: &'a M,
    grid: &'a crate::grid::GridSpec,
    g_nodes: &'a [Node],
    dt: f64,
    s: &'a State,
    mat: &'a Material,
    w: &'a Work,
    first: usize,
    g: GradChunk<'a>,
}

impl<M: Constitutive> WithLanes for ParticleAdjoint<'_, M> {
    type Output = bool;

    #[inline(always)]
    fn with<L: Lanes>(self, l: L) -> bool {
        let ParticleAdjoint {
            model,
            grid,
            g_nodes,
            dt,
            s,
            mat,
            w,
            first,
            g: (gx, gv, gc, gf, gmass, gvol, gmu, glam, gfam),
        } = self;
        for (i, gx) in gx.iter_mut().enumerate() {
            let p = first + i;
            let extra = w.extra.as_ref().map_or(DVec3::ZERO, |e| e[p]);
            let (c, f, tau) = (&s.c[p], &s.f[p], &w.tau[p]);
            let pg = p2g::p2g_adjoint_particle(
                l,
                &p2g::P2gAdjoint {
                    grid,
                    g_nodes,
                    dt,
                    x: s.x[p],
                    v: s.v[p],
                    c,
                    tau,
                    mass: mat.mass[p],
                    volume: mat.volume[p],
                    extra,
                },
            );
            let model = &crate::models::particle_model(model, &mat.family, p);
            let f_tmp = model.predict(c, f, dt);
            let (mu, lam) = (mat.mu[p], mat.lam[p]);
            let aux = if M::STRESS_AUX { w.aux[p] } else { 0.0 };
            let mg = model.update_adjoint_given_stress(
                &f_tmp,
                c,
                mu,
                lam,
                dt,
                (tau, aux),
                &gf[i],
                &pg.tau,
            );
            let (gc_pred, gf_new) = model.predict_adjoint(c, f, dt, &mg.f_tmp);
            *gx += pg.x;
            gv[i] = pg.v;
            gc[i] = pg.c + mg.c + gc_pred;
            gf[i] = gf_new;
            gmass[i] += pg.mass;
            gvol[i] += pg.volume;
            gmu[i] += mg.mu;
            glam[i] += mg.lam;
            if M::HAS_FAMILY_PARAMS {
                gfam[i] = mg.family;
            } else {
                debug_assert_eq!(
                    mg.family,
                    FamilyGrad::default(),
                    "{} has family gradients",
                    M::NAME
                );
            }
        }
        use bytemuck::cast_slice;
        any_non_finite(l, cast_slice(gx))
            || any_non_finite(l, cast_slice(gv))
            || any_non_finite(l, cast_slice(gc))
            || any_non_finite(l, cast_slice(gf))
    }
}

/// Scratch buffers of the backward pass (reused across substeps).
#[derive(Debug, Default)]
pub(crate) struct AdjointWork {
    pub(crate) fwd: Work,
    g_vgrid: Vec<NodeVel>,
    /// Nodes of `g_vgrid` the last substep wrote (zero elsewhere).
    g_active: NodeBox,
    g_nodes: Vec<Node>,
    /// `x̄` after the G2P adjoint, in bin order.
    g2p: Vec<DVec3>,
    family: Vec<FamilyGrad>,
}

impl<M: Constitutive> Simulator<M> {
    /// Backpropagates one substep: given the state `s` at time `t` (s) and `∂L/∂s_{k+1}`, returns
    /// `∂L/∂s_k` and adds the material and family gradients of this substep to `gmat`.
    /// Positions must lie inside the domain (as every state a run produces does).
    pub fn substep_backward(
        &self,
        s: &State,
        mat: &Material,
        t: f64,
        g_next: &StateGrad,
        gmat: &mut MaterialGrad,
    ) -> Result<StateGrad, MpmError> {
        self.validate(s, mat)?;
        if let Some(index) = s.x.iter().position(|x| !self.grid.domain.contains(*x)) {
            return Err(MpmError::OutsideDomain {
                index,
                position: s.x[index].to_array(),
            });
        }
        if !g_next.has_len(s.len()) {
            return Err(MpmError::GradientMismatch(
                "gradient length differs from the particle count",
            ));
        }
        if gmat.mass.len() != s.len()
            || gmat.volume.len() != s.len()
            || gmat.mu.len() != s.len()
            || gmat.lam.len() != s.len()
        {
            return Err(MpmError::GradientMismatch(
                "material gradient length differs from the particle count",
            ));
        }
        let mut g = g_next.clone();
        self.substep_backward_with(s, mat, t, &mut g, gmat, &mut AdjointWork::default(), None);
        Ok(g)
    }

    /// [`Self::substep_backward`] in place: `g` holds `∂L/∂s_{k+1}` on entry and `∂L/∂s_k` on
    /// return. Every pass reads only its own particle's entries of `g` after the previous pass
    /// consumed the others, so no second gradient state is needed. `kept` = this substep's
    /// forward intermediates when the caller still has them (else they are recomputed).
    /// Returns whether some entry of the new `g` is NaN/Inf.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn substep_backward_with(
        &self,
        s: &State,
        mat: &Material,
        t: f64,
        g: &mut StateGrad,
        gmat: &mut MaterialGrad,
        aw: &mut AdjointWork,
        kept: Option<&Work>,
    ) -> bool {
        let dt = self.config.dt;
        let grid = &self.grid;
        // Recompute τ, P2G and the grid update unless kept; G2P is folded into its adjoint.
        let w = match kept {
            Some(w) => w,
            None => {
                self.stress(s, mat, &mut aw.fwd);
                self.to_grid(s, mat, t, &mut aw.fwd);
                &aw.fwd
            }
        };
        let v_max = w
            .active
            .rows(grid)
            .flat_map(|r| &w.vgrid[r])
            .fold(0.0, |m: f64, v| m.max(v.v.abs().max_element()));
        let scale = grid.domain.lo.abs().max(grid.domain.hi.abs()).max_element();
        let reach = dt * v_max * (1.0 + 1e-9) + 1e-12 * (1.0 + scale);
        // G2P and the position update x' = hold(x + dt v'): x̄' passes where x' was not held,
        // v̄' = v̄ + dt x̄'; x̄ gets the weight and offset terms; the node gradients v̄_i are
        // scattered in the same pass. x̄ goes to `aw.g2p` in bin order, then to g.x; v̄' only feeds
        // the node gradients (v_k's gradient comes from P2G, below).
        // Only the nodes of the particles' box (`w.active`) receive gradients: zero those the
        // last substep wrote rather than the whole grid.
        if aw.g_vgrid.len() == grid.len() {
            aw.g_active.fill(grid, &mut aw.g_vgrid, NodeVel::default());
        } else {
            aw.g_vgrid.clear();
            aw.g_vgrid.resize(grid.len(), NodeVel::default());
        }
        aw.g_active = w.active.clone();
        let isa = Isa::detect();
        aw.g2p.resize(s.len(), DVec3::ZERO);
        {
            let (gx_in, gv_in, gc_in) = (&g.x, &g.v, &g.c);
            scatter_with_slabs(
                grid,
                &w.bins,
                &mut aw.g_vgrid,
                &mut aw.g2p,
                |ps, out, chunk, first| {
                    isa.run_lanes_avx512(g2p::G2pAdjoint {
                        grid,
                        vgrid: &w.vgrid,
                        ps,
                        out,
                        chunk,
                        first,
                        dt,
                        reach,
                        x: &s.x,
                        gx: gx_in,
                        gv: gv_in,
                        gc: gc_in,
                    })
                },
            );
        }
        for (&p, &gx) in w.bins.order.iter().zip(&aw.g2p) {
            g.x[p as usize] = gx;
        }
        grid_update::grid_update_adjoint(
            grid,
            &w.nodes,
            &aw.g_vgrid,
            &w.active,
            dt,
            self.config.gravity,
            &self.config.boundaries,
            &mut aw.g_nodes,
        );
        // P2G, constitutive model and strain prediction, per particle.
        let model = &self.model;
        let g_nodes = &aw.g_nodes;
        // Family gradients are stored only for models that have family scalars; the others
        // get empty chunks (their gradient is checked to be zero).
        let family = chunks_or_empty(
            &mut aw.family,
            s.len(),
            PARTICLE_CHUNK,
            M::HAS_FAMILY_PARAMS,
        );
        let non_finite = (
            g.x.par_chunks_mut(PARTICLE_CHUNK),
            g.v.par_chunks_mut(PARTICLE_CHUNK),
            g.c.par_chunks_mut(PARTICLE_CHUNK),
            g.f.par_chunks_mut(PARTICLE_CHUNK),
            gmat.mass.par_chunks_mut(PARTICLE_CHUNK),
            gmat.volume.par_chunks_mut(PARTICLE_CHUNK),
            gmat.mu.par_chunks_mut(PARTICLE_CHUNK),
            gmat.lam.par_chunks_mut(PARTICLE_CHUNK),
            family,
        )
            .into_par_iter()
            .enumerate()
            .map(|(k, g)| {
                isa.run_lanes(ParticleAdjoint {
                    model,
                    grid,
                    g_nodes,
                    dt,
                    s,
                    mat,
                    w,
                    first: k * PARTICLE_CHUNK,
                    g,
                })
            })
            .reduce(|| false, |a, b| a | b);
        // Family gradients are summed in particle order (bit-identical for any thread count).
        if M::HAS_FAMILY_PARAMS {
            gmat.family = aw.family.iter().fold(gmat.family, |acc, &f| acc + f);
            gmat.family_per_particle
                .resize(s.len(), FamilyGrad::default());
            for (acc, &f) in gmat.family_per_particle.iter_mut().zip(&aw.family) {
                *acc = *acc + f;
            }
        }
        non_finite
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::Ordering;

    use glam::DVec3;

    use crate::isa::CAP;
    use crate::{
        Aabb, BackwardOptions, Constitutive, FixedCorotated, Gradients, Material, NeoHookean,
        SimConfig, Simulator, State, StateGrad,
    };

    /// A taped forward and its backward under instruction-set cap `cap` ([`CAP`]): a blob in
    /// the middle plus particles next to each domain wall moving out of it (the held-position
    /// branch of the G2P adjoint).
    fn forward_and_backward<M: Constitutive>(model: M, cap: u8) -> (State, Gradients) {
        CAP.store(cap, Ordering::Relaxed);
        let sim = Simulator::new(
            model,
            SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.05, 1e-4),
        )
        .unwrap();
        let mut x = Vec::new();
        for i in 0..600u32 {
            let h = |k: u32| (i.wrapping_mul(2_654_435_761).rotate_left(k) % 1000) as f64 / 1e3;
            x.push(DVec3::new(
                0.35 + 0.3 * h(0),
                0.35 + 0.3 * h(11),
                0.35 + 0.3 * h(22),
            ));
        }
        let walls = [
            (DVec3::new(0.0, 0.5, 0.5), DVec3::NEG_X),
            (DVec3::new(1.0, 0.5, 0.5), DVec3::X),
            (DVec3::new(0.5, 1.0, 0.5), DVec3::Y),
            (DVec3::new(0.5, 0.5, 0.0), DVec3::NEG_Z),
        ];
        let mut s = State::at_rest(x);
        for (p, dir) in walls {
            s.x.push(p - dir * 1e-4);
            s.v.push(dir * 3.0);
            s.c.push(glam::DMat3::ZERO);
            s.f.push(glam::DMat3::IDENTITY);
        }
        let n = s.len();
        for (k, v) in s.v.iter_mut().enumerate().take(600) {
            *v = DVec3::new(0.5, -0.2 * (k % 7) as f64, 0.1);
        }
        let mat = Material::from_e_nu(n, 1e-5, 1000.0, 2e5, 0.3).unwrap();
        let tape = sim.forward_tape(&mut s, &mat, 0.0, 8, 3).unwrap();
        let mut seed = StateGrad::zeros(n);
        for (k, g) in seed.x.iter_mut().enumerate() {
            *g = DVec3::new(1.0, (k % 3) as f64, -0.5);
        }
        let g = sim
            .backward(
                &tape,
                &mat,
                |k, _| (k == 8).then(|| seed.clone()),
                BackwardOptions::default(),
            )
            .unwrap();
        CAP.store(0, Ordering::Relaxed);
        (s, g)
    }

    fn same_bits<M: Constitutive>(model: M) {
        let best = forward_and_backward(model.clone(), 0);
        for cap in [1, 2] {
            let other = forward_and_backward(model.clone(), cap);
            assert_eq!(best.0, other.0, "{} state, cap {cap}", M::NAME);
            assert_eq!(best.1.state, other.1.state, "{} ∂L/∂s₀, cap {cap}", M::NAME);
            assert_eq!(
                best.1.material,
                other.1.material,
                "{} material gradient, cap {cap}",
                M::NAME
            );
        }
        assert!(best.1.state.x.iter().any(|g| g.length() > 0.0));
    }

    /// The forward and the backward give the same bits with AVX-512, AVX2 + FMA and the
    /// baseline instructions (each fused multiply-add is exactly rounded and every sum runs in
    /// one order): the instruction set is a speed choice, never a result choice.
    #[test]
    fn every_instruction_set_gives_the_same_bits() {
        same_bits(NeoHookean);
        same_bits(FixedCorotated);
    }
}
