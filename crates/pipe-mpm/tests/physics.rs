//! Physical sanity: free fall follows x0 + v0 t − ½ g t² (to the symplectic-Euler offset
//! ½ g dt t) before any contact; an elastic block resting on sticky ground stays put; without
//! gravity and walls the transfers conserve linear momentum to round-off.

use glam::{DMat3, DVec3};
use pipe_mpm::{
    Aabb, Boundaries, BoundaryKind, Collider, Material, NeoHookean, SimConfig, Simulator, State,
    VonMises,
};

fn block(corner: DVec3, n: [usize; 3], spacing: f64) -> Vec<DVec3> {
    let mut x = Vec::new();
    for i in 0..n[0] {
        for j in 0..n[1] {
            for k in 0..n[2] {
                x.push(corner + DVec3::new(i as f64, j as f64, k as f64) * spacing);
            }
        }
    }
    x
}

#[test]
fn free_fall_matches_ballistics() {
    let dt = 2e-4;
    let sim = Simulator::new(
        NeoHookean,
        SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.05, dt),
    )
    .unwrap();
    let x0 = block(DVec3::new(0.4, 0.7, 0.4), [4, 4, 4], 0.025);
    let v0 = DVec3::new(0.3, 0.5, -0.2);
    let mut s = State::at_rest(x0.clone());
    s.v.iter_mut().for_each(|v| *v = v0);
    let mat = Material::from_e_nu(s.len(), 1.5e-5, 1000.0, 1e5, 0.3).unwrap();
    let k = 500;
    sim.run(&mut s, &mat, 0.0, k).unwrap();
    let t = k as f64 * dt;
    let g = DVec3::new(0.0, -9.8, 0.0);
    for (x, x0) in s.x.iter().zip(&x0) {
        let want = *x0 + v0 * t + 0.5 * g * t * t;
        // Symplectic Euler: x_k = x0 + v0 t + ½ g t² + ½ g dt t.
        let offset = 0.5 * g * dt * t;
        assert!(
            (*x - want - offset).abs().max_element() < 1e-12,
            "{x:?} vs {want:?}"
        );
    }
    for v in &s.v {
        let e = (*v - (v0 + g * t)).abs().max_element();
        // 500 substeps of round-off in p/m (each ~1e-16 relative).
        assert!(e < 1e-10, "velocity error {e:e}");
    }
}

#[test]
fn block_at_rest_on_ground_stays_at_rest() {
    let dx = 0.05;
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), dx, 2e-4);
    cfg.boundaries = Boundaries {
        colliders: vec![Collider::ground(0.0, BoundaryKind::Sticky)],
        walls: None,
    };
    let sim = Simulator::new(NeoHookean, cfg).unwrap();
    let x0 = block(DVec3::new(0.4, dx / 4.0, 0.4), [8, 8, 8], dx / 2.0);
    let mut s = State::at_rest(x0.clone());
    let mat = Material::from_e_nu(s.len(), (dx / 2.0f64).powi(3), 1000.0, 1e6, 0.3).unwrap();
    sim.run(&mut s, &mat, 0.0, 250).unwrap();
    let disp =
        s.x.iter()
            .zip(&x0)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
    let vmax = s.v.iter().map(|v| v.length()).fold(0.0, f64::max);
    assert!(disp < 1e-3, "block moved {disp} m");
    assert!(vmax < 0.05, "block moving at {vmax} m/s");
    assert!(s.x.iter().all(|x| x.y > -1e-9));
}

#[test]
fn momentum_is_conserved_without_gravity_and_walls() {
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), 0.05, 2e-4);
    cfg.gravity = DVec3::ZERO;
    cfg.boundaries = Boundaries::default();
    let sim = Simulator::new(
        VonMises {
            yield_stress: 200.0,
            eta: 1.0,
        },
        cfg,
    )
    .unwrap();
    let mut s = State::at_rest(block(DVec3::new(0.4, 0.4, 0.4), [5, 5, 5], 0.025));
    for (p, (v, c)) in s.v.iter_mut().zip(s.c.iter_mut()).enumerate() {
        let a = p as f64;
        *v = DVec3::new((a * 0.37).sin(), (a * 0.91).cos(), (a * 0.13).sin()) * 0.5;
        *c = DMat3::from_cols(
            DVec3::new((a * 1.3).sin(), 0.2, -0.1),
            DVec3::new(0.1, (a * 0.7).cos(), 0.3),
            DVec3::new(-0.2, 0.1, (a * 0.5).sin()),
        );
    }
    let mat = Material::from_e_nu(s.len(), 1.5e-5, 1000.0, 1e5, 0.3).unwrap();
    let p = |s: &State| -> DVec3 { s.v.iter().zip(&mat.mass).map(|(v, m)| *v * *m).sum() };
    let p0 = p(&s);
    sim.run(&mut s, &mat, 0.0, 50).unwrap();
    let p1 = p(&s);
    assert!((p1 - p0).abs().max_element() < 1e-14, "{p0:?} -> {p1:?}");
}
