//! Reverse mode by hand: one adjoint per kernel, chained backwards through a substep
//! (`crate::wide::adjoint`, on the vectorised engine), plus checkpointed multi-substep
//! backpropagation ([`Tape`]).

mod checkpoint;
pub(crate) mod schedule;

pub(crate) use checkpoint::GradArrays;
pub use checkpoint::{BackwardOptions, Gradients, SeedGrad, SeedState, Tape};
pub(crate) use checkpoint::{GradSink, SeedSource};
pub use schedule::SEGMENT_SNAPSHOTS;

use crate::error::MpmError;
use crate::models::Constitutive;
use crate::sim::{Precision, Simulator};
use crate::state::{Material, MaterialGrad, State, StateGrad};
use crate::wide::simd::Precise;
use crate::wide::soa::Soa;
use crate::wide::tape::{AdjBuffers, MatAcc, adjoint_step, to_state_grad};
use crate::wide::{Buffers, Engine};

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
        crate::sim::on_worker(|| match self.config.precision {
            Precision::F64 => self.substep_backward_in::<f64>(s, mat, t, g_next, gmat),
            Precision::F32 => self.substep_backward_in::<f32>(s, mat, t, g_next, gmat),
        })
    }

    /// [`Self::substep_backward`] in precision `T`.
    fn substep_backward_in<T: Precise>(
        &self,
        s: &State,
        mat: &Material,
        t: f64,
        g_next: &StateGrad,
        gmat: &mut MaterialGrad,
    ) -> Result<StateGrad, MpmError> {
        let mut e = Engine::<T, M>::new(self, s, mat, Buffers::default());
        e.keep = true;
        e.load(s.len(), &e.ids.clone());
        let start = e.p.clone();
        e.regroup(false)?;
        e.grid_step(t);
        let mut g = Soa::<T>::from_grad(g_next, &e.ids);
        let mut acc = MatAcc::zeros(start.stride, M::HAS_FAMILY_PARAMS);
        let mut adj = AdjBuffers::default();
        adjoint_step(&e, &start, e.work(), &mut g, &mut acc, &mut adj);
        acc.add_into(&e.ids, gmat);
        Ok(to_state_grad(&g, &e.ids, None, StateGrad::default()).0)
    }
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use crate::isa::CapGuard;
    use crate::{
        Aabb, BackwardOptions, Constitutive, FixedCorotated, Gradients, Material, NeoHookean,
        SimConfig, Simulator, State, StateGrad,
    };

    /// A taped forward and its backward under instruction-set cap `cap` (set through `isa`,
    /// held by the caller for the whole comparison): a blob in the middle plus particles next
    /// to each domain wall moving out of it (the held-position branch of the G2P adjoint).
    fn forward_and_backward<M: Constitutive>(
        model: M,
        isa: &CapGuard,
        cap: u8,
    ) -> (State, Gradients) {
        isa.set(cap);
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
        (s, g)
    }

    fn same_bits<M: Constitutive>(model: M) {
        let isa = CapGuard::lock();
        let best = forward_and_backward(model.clone(), &isa, 0);
        for cap in [1, 2] {
            let other = forward_and_backward(model.clone(), &isa, cap);
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
