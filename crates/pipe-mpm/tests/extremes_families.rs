//! Parameter extremes for the families `extremes.rs` does not sweep. That file runs
//! neo-Hookean, fixed-corotated, rate-independent von Mises (τ_Y = 10⁻³ E) and Drucker–Prager
//! at φ = 30° over E ∈ {10², 10⁵, 10⁹} Pa × ν ∈ {0, 0.3, 0.499}. Missing were the Newtonian
//! fluid (bulk modulus κ and viscosity μ instead of E, ν), viscoplastic von Mises (η > 0, which
//! adds the viscous step limit) and its yield-stress extremes (yield at once, never yield), and
//! Drucker–Prager at other friction angles (0°: no shear strength; 80°: nearly rigid cone).
//!
//! Same scene as `extremes.rs`: a 4×4×4 block thrown down at 1 m/s onto sticky ground with one
//! particle exactly on the domain edge, 100 substeps at the step `stable_step` derives (the
//! smaller of the wave and viscous limits). Each run must stay finite, keep every particle in
//! the domain and not gain speed beyond free fall. At the range edges the refusals are typed:
//! invalid parameters name the field, and a user-fixed substep count above either limit is
//! `StepTooLarge` naming the binding limit.

mod common;

use glam::DVec3;
use pipe_mpm::{
    Aabb, Constitutive, DruckerPrager, Material, MpmError, Newtonian, SimConfig, Simulator, State,
    StepLimits, VonMises, lame, stable_step, substeps_per_frame,
};

const DX: f64 = 0.05;
const E_RANGE: [f64; 3] = [1e2, 1e5, 1e9];
const NU_RANGE: [f64; 3] = [0.0, 0.3, 0.499];

fn thrown_block() -> State {
    common::thrown_block(DX)
}

/// Runs the scene; returns the step used and which limit set it.
fn drop_block<M: Constitutive + Clone>(
    model: M,
    mat: &Material,
    what: &str,
) -> (f64, &'static str) {
    let mut s = thrown_block();
    let st = stable_step(&model, &s, mat, DX, StepLimits::default());
    let dt = st.dt();
    assert!(dt.is_finite() && dt > 0.0, "{what}: dt {dt}");
    let sim = Simulator::new(
        model,
        SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), DX, dt),
    )
    .unwrap();
    let n = 100;
    sim.run(&mut s, mat, 0.0, n)
        .unwrap_or_else(|err| panic!("{} {what}: {err}", M::NAME));
    let vmax = s.v.iter().map(|v| v.length()).fold(0.0, f64::max);
    let bound = 1.0 + 9.8 * n as f64 * dt + 1e-9;
    assert!(vmax <= bound * 1.5, "{} {what}: speed {vmax} m/s", M::NAME);
    assert!(
        s.x.iter().all(|x| sim.grid().domain.contains(*x)),
        "{} {what}: left the domain",
        M::NAME
    );
    (dt, st.limit())
}

fn volume() -> f64 {
    (DX / 2.0f64).powi(3)
}

#[test]
fn newtonian_fluid_over_bulk_modulus_and_viscosity() {
    for bulk in E_RANGE {
        for visc in [0.0, 1e-3, 1.0, 1e3] {
            let mat = Material::fluid(64, volume(), 1000.0, visc, bulk).unwrap();
            let (dt, limit) = drop_block(Newtonian, &mat, &format!("κ={bulk} μ={visc}"));
            eprintln!("newtonian κ = {bulk:e} Pa, μ = {visc:e} Pa·s: dt {dt:.2e} s ({limit})");
        }
    }
}

#[test]
fn viscoplastic_von_mises_over_e_nu_and_yield_extremes() {
    for e in E_RANGE {
        for nu in NU_RANGE {
            let mat = Material::from_e_nu(64, volume(), 1000.0, e, nu).unwrap();
            // Yields at once (τ_Y = 0), viscoplastic (η up to 10³ Pa·s), never yields.
            for (yield_stress, eta) in
                [(0.0, 0.0), (1e-3 * e, 1.0), (1e-3 * e, 1e3), (1e3 * e, 0.0)]
            {
                let what = format!("E={e} ν={nu} τ_Y={yield_stress} η={eta}");
                let (dt, limit) = drop_block(VonMises { yield_stress, eta }, &mat, &what);
                if e == 1e2 && nu == 0.3 {
                    eprintln!("von Mises {what}: dt {dt:.2e} s ({limit})");
                }
            }
        }
    }
}

#[test]
fn drucker_prager_over_e_nu_and_friction_angles() {
    for e in E_RANGE {
        for nu in NU_RANGE {
            let mat = Material::from_e_nu(64, volume(), 1000.0, e, nu).unwrap();
            for phi in [0.0, 10.0, 45.0, 80.0] {
                drop_block(
                    DruckerPrager::from_friction_angle_deg(phi),
                    &mat,
                    &format!("E={e} ν={nu} φ={phi}"),
                );
            }
        }
    }
}

#[test]
fn out_of_range_parameters_are_refused_with_the_field_named() {
    for e in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        let err = Material::from_e_nu(1, 1e-5, 1000.0, e, 0.3).unwrap_err();
        assert!(
            matches!(
                err,
                MpmError::InvalidParameter { field: "E", .. }
                    | MpmError::NonFiniteInput { field: "E", .. }
            ),
            "E = {e}: {err}"
        );
    }
    for nu in [0.5, 0.7, -1.0, f64::NAN] {
        let err = lame(1e5, nu).unwrap_err();
        assert!(
            matches!(
                err,
                MpmError::InvalidParameter { field: "nu", .. }
                    | MpmError::NonFiniteInput { field: "nu", .. }
            ),
            "ν = {nu}: {err}"
        );
    }
    // ν just inside the range is accepted (λ ≈ 1.7·10¹¹ Pa at E = 10⁹).
    assert!(lame(1e9, 0.4999).unwrap().1.is_finite());
    for (visc, bulk, field) in [
        (-1.0, 1e5, "viscosity"),
        (f64::NAN, 1e5, "viscosity"),
        (1.0, 0.0, "bulk modulus"),
        (1.0, f64::INFINITY, "bulk modulus"),
    ] {
        let err = Material::fluid(1, 1e-5, 1000.0, visc, bulk).unwrap_err();
        assert!(
            matches!(
                err,
                MpmError::InvalidParameter { field: f, .. }
                    | MpmError::NonFiniteInput { field: f, .. } if f == field
            ),
            "μ = {visc}, κ = {bulk}: {err}"
        );
    }
    let cfg = SimConfig::new(Aabb::new(DVec3::ZERO, DVec3::ONE), DX, 1e-4);
    for (model, field) in [
        (
            VonMises {
                yield_stress: 1.0,
                eta: -1.0,
            },
            "eta",
        ),
        (
            VonMises {
                yield_stress: f64::NAN,
                eta: 0.0,
            },
            "yield_stress",
        ),
    ] {
        let err = Simulator::new(model, cfg.clone()).unwrap_err();
        assert!(
            matches!(
                err,
                MpmError::InvalidParameter { field: f, .. }
                    | MpmError::NonFiniteInput { field: f, .. } if f == field
            ),
            "{model:?}: {err}"
        );
    }
    let err = Simulator::new(DruckerPrager::from_friction_angle_deg(-10.0), cfg).unwrap_err();
    assert!(
        matches!(
            err,
            MpmError::InvalidParameter {
                field: "friction_alpha",
                ..
            }
        ),
        "{err}"
    );
}

/// Half the derived substeps per frame must be refused, naming the limit that binds.
fn refuses_half<M: Constitutive>(model: &M, mat: &Material, want: &str) {
    let s = thrown_block();
    let st = stable_step(model, &s, mat, DX, StepLimits::default());
    let frame = 1.0 / 24.0;
    let n = substeps_per_frame(&st, frame, None).unwrap();
    assert_eq!(substeps_per_frame(&st, frame, Some(n)).unwrap(), n);
    match substeps_per_frame(&st, frame, Some(n.div_ceil(2))) {
        Err(MpmError::StepTooLarge { limit, dt, max_dt }) => {
            assert_eq!(limit, want, "{}", M::NAME);
            assert!(dt > max_dt);
        }
        other => panic!("{}: {other:?}", M::NAME),
    }
    eprintln!("{}: {n} substeps per frame at the {want} limit", M::NAME);
}

#[test]
fn too_few_substeps_at_the_stiff_and_viscous_ends_are_refused() {
    let stiff = Material::from_e_nu(64, volume(), 1000.0, 1e9, 0.499).unwrap();
    let wave = "elastic wave (CFL)";
    refuses_half(
        &VonMises {
            yield_stress: 1e6,
            eta: 0.0,
        },
        &stiff,
        wave,
    );
    refuses_half(&DruckerPrager::from_friction_angle_deg(30.0), &stiff, wave);
    refuses_half(
        &Newtonian,
        &Material::fluid(64, volume(), 1000.0, 1e-3, 1e9).unwrap(),
        wave,
    );
    let soft = Material::from_e_nu(64, volume(), 1000.0, 1e2, 0.3).unwrap();
    refuses_half(
        &VonMises {
            yield_stress: 0.1,
            eta: 1e3,
        },
        &soft,
        "viscous",
    );
    refuses_half(
        &Newtonian,
        &Material::fluid(64, volume(), 1000.0, 1e3, 1e2).unwrap(),
        "viscous",
    );
}
