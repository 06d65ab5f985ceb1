//! Sand (Drucker–Prager, cohesionless) piles up at a slope set by its friction angle.
//!
//! Main scene: a sand column as tall as its radius (r₀ = h₀ = 0.1 m; φ = 30°, E = 2·10⁵ Pa,
//! ν = 0.3, ρ = 1600 kg/m³, dx = 0.02 m, two particles per cell per axis) released on sticky
//! ground, run for 1.5 s at the crate's stable step per 10 ms frame. Only a quarter of the
//! column is simulated: the planes x = x_c and z = z_c through its axis are slip box colliders
//! (no normal velocity at and behind the plane), the mirror conditions of the axisymmetric
//! collapse, so 790 particles give the full 3D pile in a few seconds. A 3D (axisymmetric)
//! pile is used on purpose: this α(φ) = √(2/3)·2 sin φ/(3 − sin φ) matches Mohr–Coulomb in
//! triaxial compression, while in plane strain it is much stronger (see the last test).
//! An aspect ratio of 1 keeps the collapse gentle; taller columns spread by inertia and end
//! flatter (r₀ = 0.1, h₀ = 0.2 m gave a 20° pile for φ = 30°).
//!
//! Measured: the top particle height in half-cell radius bins; the flank is the least-squares
//! line through the bins between 20 % and 80 % of the pile height, its angle the slope; the overall
//! angle is atan(H / runout radius). Results (φ = 30°): flank 25.6°, overall 23.7° at
//! dx = 0.02 m; 24.5° and 23.0° at dx = 0.01 m (6320 particles, ignored test, ~40 s), so the
//! value is resolution-converged to ~1°: a column collapse ends about 5° below φ, as dynamic
//! collapses do. Asserted: within ±10° of φ. φ = 20° / 40° give 12.8° / 32.0°.

use glam::DVec3;
use pipe_mpm::{
    Aabb, Boundaries, BoundaryKind, Collider, DruckerPrager, Material, SimConfig, Simulator, State,
    StepLimits, stable_step,
};

const RHO: f64 = 1600.0;
const E: f64 = 2e5;
const NU: f64 = 0.3;
const FRAME: f64 = 0.01;

/// Runs `seconds` at the stable step of the current state, one 10 ms frame at a time.
fn settle(
    sim: &mut Simulator<DruckerPrager>,
    s: &mut State,
    mat: &Material,
    seconds: f64,
) -> usize {
    let dx = sim.grid().dx;
    let (mut t, mut substeps) = (0.0, 0);
    while t < seconds - 1e-9 {
        let k =
            stable_step(sim.model(), s, mat, dx, StepLimits::default()).substeps_per_frame(FRAME);
        sim.set_dt(FRAME / k as f64).unwrap();
        sim.run(s, mat, t, k).unwrap();
        t += FRAME;
        substeps += k;
    }
    substeps
}

/// Least-squares slope angle (degrees, positive when the height falls with `r`) through the
/// `(r, height)` points whose height lies between 20 % and 80 % of `h`.
fn flank_angle(profile: &[(f64, f64)], h: f64) -> (f64, usize) {
    let pts: Vec<_> = profile
        .iter()
        .filter(|p| p.1 > 0.2 * h && p.1 < 0.8 * h)
        .collect();
    let n = pts.len() as f64;
    let mr = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let mh = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let sxy: f64 = pts.iter().map(|p| (p.0 - mr) * (p.1 - mh)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mr) * (p.0 - mr)).sum();
    ((-sxy / sxx).atan().to_degrees(), pts.len())
}

/// Top particle height above the ground per bin of `bin` metres in the coordinate `r(x)`.
fn profile(s: &State, ground: f64, bin: f64, r: impl Fn(DVec3) -> f64) -> Vec<(f64, f64)> {
    let mut top: Vec<Option<f64>> = Vec::new();
    for x in &s.x {
        let b = (r(*x) / bin) as usize;
        if top.len() <= b {
            top.resize(b + 1, None);
        }
        let y = x.y - ground;
        top[b] = Some(top[b].map_or(y, |t: f64| t.max(y)));
    }
    top.iter()
        .enumerate()
        .filter_map(|(b, t)| t.map(|t| ((b as f64 + 0.5) * bin, t)))
        .collect()
}

#[derive(Debug)]
struct Pile {
    flank_deg: f64,
    overall_deg: f64,
    height: f64,
    runout: f64,
    vmax: f64,
    lowest: f64,
}

fn quarter_pile(phi: f64, dx: f64) -> Pile {
    let clock = std::time::Instant::now();
    let (r0, h0) = (0.1, 0.1);
    let ground = 3.0 * dx;
    let axis = DVec3::new(0.1, 0.0, 0.1);
    let mut cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::new(0.6, 0.4, 0.6)), dx, 1e-4);
    let mirror = |hi: DVec3| Collider::Box {
        aabb: Aabb::new(DVec3::splat(-2.0), hi),
        kind: BoundaryKind::Slip,
    };
    // The boxes end 1 nm past the mirror planes so that the nodes on the planes are included.
    cfg.boundaries = Boundaries {
        colliders: vec![
            Collider::ground(ground, BoundaryKind::Sticky),
            mirror(DVec3::new(axis.x + 1e-9, 3.0, 3.0)),
            mirror(DVec3::new(3.0, 3.0, axis.z + 1e-9)),
        ],
        walls: Some(BoundaryKind::Slip),
    };
    let model = DruckerPrager::from_friction_angle_deg(phi);
    let mut sim = Simulator::new(model, cfg).unwrap();
    let sp = dx / 2.0;
    let (nr, ny) = ((r0 / sp).round() as usize, (h0 / sp).round() as usize);
    let mut x = Vec::new();
    for i in 0..nr {
        for k in 0..nr {
            let (a, b) = ((i as f64 + 0.5) * sp, (k as f64 + 0.5) * sp);
            if a * a + b * b <= r0 * r0 {
                for j in 0..ny {
                    x.push(DVec3::new(
                        axis.x + a,
                        ground + (j as f64 + 0.5) * sp,
                        axis.z + b,
                    ));
                }
            }
        }
    }
    let mut s = State::at_rest(x);
    let mat = Material::from_e_nu(s.len(), sp * sp * sp, RHO, E, NU).unwrap();
    let substeps = settle(&mut sim, &mut s, &mat, 1.5);
    let radius = |x: DVec3| ((x.x - axis.x).powi(2) + (x.z - axis.z).powi(2)).sqrt();
    let prof = profile(&s, ground, sp, radius);
    let height = prof.iter().map(|p| p.1).fold(0.0, f64::max);
    let (flank_deg, bins) = flank_angle(&prof, height);
    let runout = s.x.iter().map(|x| radius(*x)).fold(0.0, f64::max);
    let pile = Pile {
        flank_deg,
        overall_deg: (height / runout).atan().to_degrees(),
        height,
        runout,
        vmax: s.v.iter().map(|v| v.length()).fold(0.0, f64::max),
        lowest: s.x.iter().map(|x| x.y - ground).fold(f64::MAX, f64::min),
    };
    eprintln!(
        "phi {phi}°, dx {dx} m, {} particles: {pile:?} (flank fit over {bins} bins), {substeps} \
         substeps in {:.2?}",
        s.len(),
        clock.elapsed()
    );
    pile
}

fn check_pile(phi: f64, p: &Pile) {
    assert!(
        (p.flank_deg - phi).abs() <= 10.0,
        "flank {:.1}° for φ = {phi}°",
        p.flank_deg
    );
    assert!(
        (p.overall_deg - phi).abs() <= 10.0,
        "overall {:.1}° for φ = {phi}°",
        p.overall_deg
    );
    assert!(p.runout > 0.12 && p.height < 0.1, "did not collapse: {p:?}");
    assert!(p.vmax < 0.02, "not settled: {p:?}");
    assert!(p.lowest > -0.02, "below the ground: {p:?}");
}

#[test]
fn sand_column_collapses_to_a_pile_near_its_friction_angle() {
    let p = quarter_pile(30.0, 0.02);
    check_pile(30.0, &p);
}

#[test]
fn a_larger_friction_angle_gives_a_steeper_pile() {
    let low = quarter_pile(20.0, 0.02);
    let high = quarter_pile(40.0, 0.02);
    assert!(
        high.flank_deg > low.flank_deg + 10.0 && high.overall_deg > low.overall_deg + 4.0,
        "φ = 20°: {low:?}; φ = 40°: {high:?}"
    );
    assert!(high.runout < low.runout, "{low:?} vs {high:?}");
}

/// ~40 s: `cargo test -p pipe-mpm --test physics_sand -- --ignored`.
#[test]
#[ignore = "heavy (6320 particles, ~40 s); run with --ignored"]
fn sand_pile_at_twice_the_resolution() {
    let p = quarter_pile(30.0, 0.01);
    check_pile(30.0, &p);
}

/// Plane strain (a one-cell slab whose two z faces are slip box colliders, so every node has
/// v_z = 0 and F_zz stays 1): a 20° sand wedge with φ = 30° must stand still once gravity has
/// loaded it elastically, and a 60° wedge must fall. In plane strain this DP cone is stronger
/// than φ (its Mohr–Coulomb equivalent there is ≈ 44°–49°, depending on the flow rule; a 45°
/// wedge stood at 46.7° and a 55° one fell to 32.9° in trial runs), so the steep case is 60°.
/// Without the z colliders (slip domain walls only act outside the domain) the thin slab
/// expands sideways, loses its confining pressure, and even the 20° wedge slumps to ~11°.
#[test]
fn plane_strain_wedge_below_the_friction_angle_stands_and_a_steep_one_falls() {
    let dx = 0.02;
    let ground = 3.0 * dx;
    let z0 = 0.2;
    let run = |slope_deg: f64, half_base: f64| -> (f64, f64, f64) {
        let mut cfg = SimConfig::new(
            Aabb::new(DVec3::new(0.0, 0.0, z0), DVec3::new(1.0, 0.5, z0 + dx)),
            dx,
            1e-4,
        );
        cfg.boundaries = Boundaries {
            colliders: vec![
                Collider::ground(ground, BoundaryKind::Sticky),
                Collider::Box {
                    aabb: Aabb::new(DVec3::splat(-2.0), DVec3::new(3.0, 3.0, z0 + 1e-9)),
                    kind: BoundaryKind::Slip,
                },
                Collider::Box {
                    aabb: Aabb::new(DVec3::new(-2.0, -2.0, z0 + dx - 1e-9), DVec3::splat(3.0)),
                    kind: BoundaryKind::Slip,
                },
            ],
            walls: Some(BoundaryKind::Slip),
        };
        let model = DruckerPrager::from_friction_angle_deg(30.0);
        let mut sim = Simulator::new(model, cfg).unwrap();
        let sp = dx / 2.0;
        let xc = 0.5;
        let tan = slope_deg.to_radians().tan();
        let n = (2.0 * half_base / sp).round() as usize;
        let mut x = Vec::new();
        for i in 0..n {
            let px = xc - half_base + (i as f64 + 0.5) * sp;
            let top = (half_base - (px - xc).abs()) * tan;
            for j in 0.. {
                let py = (j as f64 + 0.5) * sp;
                if py > top {
                    break;
                }
                for k in 0..2 {
                    x.push(DVec3::new(px, ground + py, z0 + (k as f64 + 0.5) * sp));
                }
            }
        }
        let x0 = x.clone();
        let mut s = State::at_rest(x);
        let mat = Material::from_e_nu(s.len(), sp * sp * sp, RHO, E, NU).unwrap();
        settle(&mut sim, &mut s, &mat, 1.0);
        let prof = profile(&s, ground, sp, |x| (x.x - xc).abs());
        let h = prof.iter().map(|p| p.1).fold(0.0, f64::max);
        let disp =
            s.x.iter()
                .zip(&x0)
                .map(|(a, b)| (*a - *b).length())
                .fold(0.0, f64::max);
        let vmax = s.v.iter().map(|v| v.length()).fold(0.0, f64::max);
        let (flank, _) = flank_angle(&prof, h);
        eprintln!(
            "plane-strain wedge {slope_deg}° (φ = 30°): flank {flank:.1}°, max displacement \
             {disp:.4} m, max speed {vmax:.1e} m/s, {} particles",
            s.len()
        );
        (flank, disp, vmax)
    };
    let (flank, disp, vmax) = run(20.0, 0.3);
    assert!((flank - 20.0).abs() < 2.0, "20° wedge: flank {flank}°");
    assert!(disp < 0.25 * dx, "20° wedge moved {disp} m");
    assert!(vmax < 1e-3, "20° wedge still moving at {vmax} m/s");
    let (flank, disp, _) = run(60.0, 0.15);
    assert!(
        flank < 45.0 && disp > 2.0 * dx,
        "60° wedge stood: {flank}°, {disp} m"
    );
}
