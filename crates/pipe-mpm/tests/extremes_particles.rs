//! Extreme particle configurations: particles fired at the domain walls at high speed under
//! every wall treatment, a single particle, and 10⁶ particles crammed into one grid cell.
//!
//! Why these scenes. Lone particles fired along all 26 face / edge / corner directions reach
//! every wall and corner of the domain, where the stencil reaches into the margin nodes — the
//! place an out-of-range index or a lost particle would show; a small elastic block is fired too,
//! so stress and the deformation gradient meet the wall, not only free transport. They run at the
//! crate's stable step for 50, 10³ and 10⁵ m/s (every particle must stay finite, inside, and be
//! held and counted), and once with a step 67× the limit, so that a particle jumps farther than
//! the whole grid in one substep: only the domain hold keeps the stencil in range, and a blow-up
//! must come back as the typed `NonFinite` error, never a panic. A single particle is the
//! smallest valid input: its free fall must be ballistic and it must come to rest on the ground.
//! A million particles in one cell put the whole scatter into one slab and every particle into
//! the same 27 nodes, with node masses summed from 10⁶ tiny contributions: the substeps must stay
//! finite and change the momentum by exactly `M g t`.

use glam::{DMat3, DVec3};
use pipe_mpm::{
    Aabb, Boundaries, BoundaryKind, Collider, Material, MpmError, NeoHookean, SimConfig, Simulator,
    State, StepLimits, stable_step,
};

/// The 26 unit directions towards the faces, edges and corners of a cube.
fn directions() -> Vec<DVec3> {
    let mut d = Vec::new();
    for i in -1..=1 {
        for j in -1..=1 {
            for k in -1..=1 {
                if (i, j, k) != (0, 0, 0) {
                    d.push(DVec3::new(i as f64, j as f64, k as f64).normalize());
                }
            }
        }
    }
    d
}

/// Lone particles fired from near the centre along the 26 directions, plus a 3×3×3 block fired
/// at the +x wall; everything at `speed` (m/s).
fn fired(centre: DVec3, speed: f64, dx: f64) -> State {
    let mut x = Vec::new();
    let mut v = Vec::new();
    for d in directions() {
        x.push(centre + 0.15 * d);
        v.push(speed * d);
    }
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..3 {
                x.push(
                    centre
                        + DVec3::new(0.02, -0.05, -0.05)
                        + DVec3::new(i as f64, j as f64, k as f64) * (dx / 2.0),
                );
                v.push(DVec3::new(speed, 0.1 * speed, 0.0));
            }
        }
    }
    let mut s = State::at_rest(x);
    s.v = v;
    s
}

fn wall_config(walls: Option<BoundaryKind>, dx: f64, dt: f64) -> SimConfig {
    let mut cfg = SimConfig::new(Aabb::new(DVec3::splat(0.2), DVec3::splat(0.8)), dx, dt);
    cfg.boundaries = Boundaries {
        colliders: Vec::new(),
        walls,
    };
    cfg
}

const KINDS: [Option<BoundaryKind>; 4] = [
    None,
    Some(BoundaryKind::Sticky),
    Some(BoundaryKind::Slip),
    Some(BoundaryKind::Separate),
];

#[test]
fn particles_fired_at_the_walls_stay_inside_at_the_stable_step() {
    let dx = 0.05;
    for (speed, walls) in [50.0, 1e3, 1e5]
        .into_iter()
        .flat_map(|sp| KINDS.map(|k| (sp, k)))
    {
        let mut s = fired(DVec3::splat(0.5), speed, dx);
        let n = s.len();
        let mat = Material::from_e_nu(n, (dx / 2.0f64).powi(3), 1000.0, 1e5, 0.3).unwrap();
        let dt = stable_step(&NeoHookean, &s, &mat, dx, StepLimits::default()).dt();
        let sim = Simulator::new(NeoHookean, wall_config(walls, dx, dt)).unwrap();
        // 1 m of travel: the farthest wall is 0.3 m away along any axis.
        let steps = (1.0 / (speed * dt)).ceil() as usize;
        let rep = sim
            .run(&mut s, &mat, 0.0, steps)
            .unwrap_or_else(|e| panic!("walls {walls:?}: {e}"));
        let vmax = s.v.iter().map(|v| v.length()).fold(0.0, f64::max);
        eprintln!(
            "{speed} m/s, walls {walls:?}: dt {dt:.3e} s, {steps} substeps, {rep:?}, \
             vmax {vmax:.2} m/s"
        );
        assert_eq!(s.len(), n);
        assert!(s.first_non_finite().is_none());
        for x in &s.x {
            assert!(
                sim.grid().domain.contains(*x),
                "walls {walls:?}: {x:?} left the domain"
            );
        }
        // Every particle reaches the domain edge and is held there (counted): at some substep
        // all of them at once.
        assert_eq!(rep.max_held, n, "{speed} m/s, walls {walls:?}: {rep:?}");
        assert!(rep.held >= n, "{rep:?}");
        // Without walls nothing slows them; any wall treatment takes out the normal motion.
        if walls.is_none() {
            assert!(vmax >= speed, "{speed} m/s: slowed to {vmax} without walls");
        } else {
            assert!(
                vmax < 0.9 * speed,
                "{speed} m/s, walls {walls:?}: still {vmax} m/s"
            );
        }
    }
}

/// Lone particles 0.25 m from the centre along the 26 directions: neighbours are at least
/// 0.19 m (3.8 cells) apart, so no two share a grid node.
fn lone(speed: f64) -> State {
    let mut s = State::at_rest(
        directions()
            .iter()
            .map(|d| DVec3::splat(0.5) + 0.25 * *d)
            .collect(),
    );
    s.v = directions().iter().map(|d| speed * *d).collect();
    s
}

#[test]
fn a_step_that_jumps_past_the_grid_never_reads_out_of_range() {
    // dt = 1e-3 s at 1e3 m/s: 1 m per substep, more than the whole grid (0.6 m domain plus
    // 3 cells of margin per side), 67x the stable step.
    let dx = 0.05;
    let (speed, dt, steps) = (1e3, 1e-3, 20);
    for walls in KINDS {
        let mut s = lone(speed);
        let n = s.len();
        let mat = Material::from_e_nu(n, (dx / 2.0f64).powi(3), 1000.0, 1e5, 0.3).unwrap();
        let limit = stable_step(&NeoHookean, &s, &mat, dx, StepLimits::default()).dt();
        assert!(dt > 50.0 * limit);
        let sim = Simulator::new(NeoHookean, wall_config(walls, dx, dt)).unwrap();
        let res = sim.run(&mut s, &mat, 0.0, steps);
        eprintln!("walls {walls:?}: dt = {:.0} x limit: {res:?}", dt / limit);
        assert_eq!(s.len(), n);
        match (walls, res) {
            // Without walls each particle just translates (held at the edge every substep).
            (None, Ok(rep)) => {
                assert_eq!(rep.held, n * steps, "{rep:?}");
                assert!(s.first_non_finite().is_none());
                assert!(s.x.iter().all(|x| sim.grid().domain.contains(*x)));
                for (v, d) in s.v.iter().zip(directions()) {
                    let want = speed * d + DVec3::new(0.0, -9.8, 0.0) * (dt * steps as f64);
                    assert!((*v - want).length() < 1e-9 * speed, "{v:?} vs {want:?}");
                }
            }
            // With walls: finite and inside, or — as measured for all three kinds, at substep 2 —
            // the wall stops the outer nodes, the velocity gradient across the stencil inverts
            // F within one 67x-too-large step, and the run stops with the typed error.
            (Some(_), Ok(rep)) => {
                assert!(s.first_non_finite().is_none());
                assert!(
                    s.x.iter().all(|x| sim.grid().domain.contains(*x)),
                    "{rep:?}"
                );
            }
            (Some(_), Err(MpmError::NonFinite { substep, .. })) => assert!(substep < steps),
            (w, other) => panic!("walls {w:?}: {other:?}"),
        }
    }
}

#[test]
fn a_single_particle_falls_ballistically_then_rests_on_the_ground() {
    let (dx, ground, dt) = (0.05, 0.2, 2e-4);
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), dx, dt);
    cfg.boundaries = Boundaries {
        colliders: vec![Collider::ground(ground, BoundaryKind::Sticky)],
        walls: Some(BoundaryKind::Separate),
    };
    let sim = Simulator::new(NeoHookean, cfg).unwrap();
    let x0 = DVec3::new(0.5, 0.6, 0.5);
    let v0 = DVec3::new(0.1, 0.0, -0.05);
    let mut s = State::at_rest(vec![x0]);
    s.v[0] = v0;
    let mat = Material::from_e_nu(1, (dx / 2.0f64).powi(3), 1000.0, 1e5, 0.3).unwrap();
    assert!(dt <= stable_step(&NeoHookean, &s, &mat, dx, StepLimits::default()).dt());
    let g = DVec3::new(0.0, -9.8, 0.0);
    // Free fall until the stencil (1.5 cells) first reaches a ground node: exact ballistics up
    // to the symplectic-Euler offset. Round-off alone stays ~1e-14; the tolerance covers the
    // mass threshold (1e-8 dx³ kg): when the particle crosses a cell, an outer node whose weight
    // is below ~1e-10 is treated as empty and its w·v (≈ 4e-11 m/s here) is dropped.
    let mut k = 0;
    loop {
        sim.run(&mut s, &mat, k as f64 * dt, 1).unwrap();
        k += 1;
        let t = k as f64 * dt;
        if s.x[0].y - 1.5 * dx <= ground + 0.5 * dx {
            break;
        }
        let want = x0 + v0 * t + 0.5 * g * t * t + 0.5 * g * dt * t;
        assert!(
            (s.x[0] - want).length() < 1e-11,
            "t = {t}: {:?} vs {want:?}",
            s.x[0]
        );
        assert!(
            (s.v[0] - (v0 + g * t)).length() < 1e-9,
            "t = {t}: {:?}",
            s.v[0]
        );
    }
    let t_fall = k as f64 * dt;
    let impact = s.v[0].length();
    // Contact. A lone particle has no stress to stand on: the sticky ground only stops the
    // nodes at or below it, so the particle slows as more of its stencil weight sits on those
    // nodes and then creeps at a speed of order g·dt that keeps decaying; its limit is half a
    // cell below the ground, where all its nodes are sticky. Its own elastic stress (F is
    // compressed as the lower nodes stop) makes it bounce first, slower than it hit.
    let t_end = 1.5;
    let mut y_low = f64::MAX;
    let mut vy_up = 0.0f64;
    while (k as f64) * dt < t_end {
        sim.run(&mut s, &mat, k as f64 * dt, 1).unwrap();
        k += 1;
        y_low = y_low.min(s.x[0].y);
        vy_up = vy_up.max(s.v[0].y);
    }
    let v = s.v[0];
    eprintln!(
        "single particle: ballistic to 1e-11 m until t = {t_fall:.4} s, then {impact:.3} m/s; \
         at t = {t_end} s: y - ground = {:.5} m, v = {v:?}, lowest y - ground = {:.5} m, \
         largest rebound speed {vy_up:.4} m/s",
        s.x[0].y - ground,
        y_low - ground
    );
    assert!(vy_up < impact, "rebound {vy_up} m/s faster than the impact");
    assert!(s.first_non_finite().is_none());
    assert!(v.length() < 0.01 * impact, "still moving: {v:?}");
    assert!(v.x.abs() < 1e-12 && v.z.abs() < 1e-12, "sliding: {v:?}");
    assert!(y_low > ground - 0.5 * dx, "sank to {y_low}");
    // Grid contact acts within the stencil's reach (1.5 cells), not at the plane itself.
    assert!(s.x[0].y < ground + 1.5 * dx, "floating at {}", s.x[0].y);
}

/// `n` particles spread over the cell `[corner, corner + dx)³` by a deterministic low-discrepancy
/// sequence, the first eight on its corners (exact cell-boundary positions), each with volume
/// `dx³/n`, random velocities up to 1 m/s and random affine `C` up to 10 /s.
fn crowded_cell(n: usize, corner: DVec3, dx: f64) -> (State, Material) {
    // R3 sequence (golden ratio generalisation) and a small LCG for velocities.
    let a = [
        0.819_172_513_396_164_4,
        0.671_043_606_703_789_2,
        0.549_700_477_901_970_4,
    ];
    let mut x = Vec::with_capacity(n);
    for p in 0..n {
        let u = if p < 8 {
            DVec3::new((p & 1) as f64, ((p >> 1) & 1) as f64, ((p >> 2) & 1) as f64) * 0.999_999
        } else {
            let q = p as f64;
            DVec3::new(
                (0.5 + a[0] * q).fract(),
                (0.5 + a[1] * q).fract(),
                (0.5 + a[2] * q).fract(),
            )
        };
        x.push(corner + u * dx);
    }
    let mut s = State::at_rest(x);
    let mut seed = 0x2545_f491_4f6c_dd1du64;
    let mut rnd = || {
        seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (seed >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    };
    for (v, c) in s.v.iter_mut().zip(s.c.iter_mut()) {
        *v = DVec3::new(rnd(), rnd(), rnd());
        *c = DMat3::from_cols_array(&std::array::from_fn(|_| 10.0 * rnd()));
    }
    let mat = Material::from_e_nu(n, dx.powi(3) / n as f64, 1000.0, 1e5, 0.3).unwrap();
    (s, mat)
}

fn run_crowded(n: usize) {
    let dx = 0.05;
    let (mut s, mat) = crowded_cell(n, DVec3::splat(0.5), dx);
    let st = stable_step(&NeoHookean, &s, &mat, dx, StepLimits::default());
    let dt = st.dt();
    // No ground or walls reach the cell: momentum changes by exactly M g t.
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), dx, dt);
    cfg.boundaries = Boundaries::default();
    let sim = Simulator::new(NeoHookean, cfg).unwrap();
    let p = |s: &State| -> DVec3 { s.v.iter().zip(&mat.mass).map(|(v, m)| *v * *m).sum() };
    let m_tot: f64 = mat.mass.iter().sum();
    let p0 = p(&s);
    let steps = 3;
    let t0 = std::time::Instant::now();
    let rep = sim.run(&mut s, &mat, 0.0, steps).unwrap();
    let elapsed = t0.elapsed();
    let p1 = p(&s);
    let want = p0 + DVec3::new(0.0, -9.8, 0.0) * (m_tot * dt * steps as f64);
    eprintln!(
        "{n} particles in one cell: dt {dt:.3e} s, {steps} substeps in {elapsed:?}, {rep:?}, \
         momentum error {:.2e} of {:.3e} kg·m/s",
        (p1 - want).length(),
        want.length()
    );
    assert_eq!(s.len(), n);
    assert_eq!(rep.held, 0);
    assert!(s.first_non_finite().is_none());
    assert!(s.x.iter().all(|x| sim.grid().domain.contains(*x)));
    assert!(
        (p1 - want).length() < 1e-9 * want.length().max(p0.length()),
        "{p1:?} vs {want:?}"
    );
}

/// 10⁶ particles: three substeps take ~0.7 s here (the whole scatter is one slab, so one
/// thread), well inside the normal suite's budget.
#[test]
fn a_million_particles_in_one_cell() {
    run_crowded(1_000_000);
}
