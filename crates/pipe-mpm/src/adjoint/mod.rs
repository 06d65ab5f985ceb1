//! Reverse mode by hand: one adjoint per kernel, chained backwards through a substep, plus
//! checkpointed multi-substep backpropagation ([`Tape`]).

mod checkpoint;
mod g2p;
mod grid_update;
mod p2g;

pub use checkpoint::{BackwardOptions, Gradients, Tape};

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::error::MpmError;
use crate::models::Constitutive;
use crate::p2g::Node;
use crate::sim::{Simulator, Work};
use crate::state::{FamilyGrad, Material, MaterialGrad, State, StateGrad};

/// Scratch buffers of the backward pass.
#[derive(Debug, Default)]
pub(crate) struct AdjointWork {
    fwd: Work,
    next: Option<State>,
    gv_new: Vec<DVec3>,
    gx_g2p: Vec<DVec3>,
    g_vgrid: Vec<DVec3>,
    g_nodes: Vec<Node>,
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
        if g_next.len() != s.len()
            || g_next.v.len() != s.len()
            || g_next.c.len() != s.len()
            || g_next.f.len() != s.len()
        {
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
        let mut aw = AdjointWork::default();
        Ok(self.substep_backward_with(s, mat, t, g_next, gmat, &mut aw))
    }

    pub(crate) fn substep_backward_with(
        &self,
        s: &State,
        mat: &Material,
        t: f64,
        g_next: &StateGrad,
        gmat: &mut MaterialGrad,
        aw: &mut AdjointWork,
    ) -> StateGrad {
        let dt = self.config.dt;
        let n = s.len();
        let grid = &self.grid;
        // Recompute the forward substep and its intermediates.
        let mut next = aw.next.take().unwrap_or_else(|| s.clone());
        self.forward(s, mat, t, &mut next, &mut aw.fwd);
        let w = &aw.fwd;
        // G2P and the position update x' = hold(x + dt v').
        let (gv_new, gx_g2p): (Vec<DVec3>, Vec<DVec3>) = (0..n)
            .into_par_iter()
            .map(|p| {
                let unclamped = s.x[p] + dt * next.v[p];
                let mask = DVec3::select(unclamped.cmpeq(next.x[p]), DVec3::ONE, DVec3::ZERO);
                let gxn = g_next.x[p] * mask;
                let gv = g_next.v[p] + dt * gxn;
                let gx = gxn + g2p::position_grad(grid, &w.vgrid, s.x[p], gv, &g_next.c[p]);
                (gv, gx)
            })
            .unzip();
        aw.gv_new = gv_new;
        aw.gx_g2p = gx_g2p;
        g2p::scatter_node_grads(grid, &w.bins, &s.x, &aw.gv_new, &g_next.c, &mut aw.g_vgrid);
        grid_update::grid_update_adjoint(
            grid,
            &w.nodes,
            &aw.g_vgrid,
            dt,
            self.config.gravity,
            &self.config.boundaries,
            &mut aw.g_nodes,
        );
        // P2G, constitutive model and strain prediction, per particle.
        let model = &self.model;
        let per: Vec<(DVec3, DVec3, DMat3, DMat3, [f64; 4], FamilyGrad)> = (0..n)
            .into_par_iter()
            .map(|p| {
                let extra = w.extra.as_ref().map_or(DVec3::ZERO, |e| e[p]);
                let pg = p2g::p2g_adjoint_particle(
                    grid,
                    &aw.g_nodes,
                    dt,
                    s.x[p],
                    s.v[p],
                    &s.c[p],
                    &w.tau[p],
                    mat.mass[p],
                    mat.volume[p],
                    extra,
                );
                let mg = model.update_adjoint(
                    &w.f_tmp[p],
                    &s.c[p],
                    mat.mu[p],
                    mat.lam[p],
                    dt,
                    &g_next.f[p],
                    &pg.tau,
                );
                let (gc_pred, gf) = model.predict_adjoint(&s.c[p], &s.f[p], dt, &mg.f_tmp);
                (
                    aw.gx_g2p[p] + pg.x,
                    pg.v,
                    pg.c + mg.c + gc_pred,
                    gf,
                    [pg.mass, pg.volume, mg.mu, mg.lam],
                    mg.family,
                )
            })
            .collect();
        let mut g = StateGrad::zeros(n);
        for (p, (gx, gv, gc, gf, m4, fam)) in per.into_iter().enumerate() {
            g.x[p] = gx;
            g.v[p] = gv;
            g.c[p] = gc;
            g.f[p] = gf;
            gmat.mass[p] += m4[0];
            gmat.volume[p] += m4[1];
            gmat.mu[p] += m4[2];
            gmat.lam[p] += m4[3];
            gmat.family = gmat.family + fam;
        }
        aw.next = Some(next);
        g
    }
}
