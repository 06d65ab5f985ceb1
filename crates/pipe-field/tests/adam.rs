//! Adam with parameter groups and learning-rate schedules: the schedule's end points and
//! geometric decay, the first step's size per group, convergence on a quadratic, and typed
//! errors that leave the parameters unchanged.

use pipe_field::{Adam, AdamConfig, FieldError, LrSchedule, ParamGroup};

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs()
}

#[test]
fn schedule_decays_exponentially_from_lr_to_lr_final() {
    let s = LrSchedule::exponential(1e-2, 1e-4, 101);
    assert_eq!(s.at(0), 1e-2);
    assert!(rel(s.at(100), 1e-4) < 1e-12);
    assert!(rel(s.at(50), 1e-3) < 1e-12, "{}", s.at(50));
    // Each step multiplies the rate by the same factor, and it stays at lr_final afterwards.
    let ratio = s.at(1) / s.at(0);
    assert!(rel(s.at(71) / s.at(70), ratio) < 1e-12);
    assert_eq!(s.at(100), s.at(1000));
    let c = LrSchedule::constant(3e-3);
    assert_eq!(c.at(0), 3e-3);
    assert_eq!(c.at(500), 3e-3);
}

fn groups(lr_a: LrSchedule, lr_b: LrSchedule) -> Vec<ParamGroup> {
    vec![
        ParamGroup {
            name: "planes",
            len: 3,
            schedule: lr_a,
        },
        ParamGroup {
            name: "mlp",
            len: 2,
            schedule: lr_b,
        },
    ]
}

#[test]
fn first_step_moves_each_value_by_its_group_rate() {
    let mut adam = Adam::new(
        AdamConfig::default(),
        groups(
            LrSchedule::exponential(0.1, 0.01, 10),
            LrSchedule::constant(0.5),
        ),
    )
    .unwrap();
    let mut a = [1.0, 2.0, 3.0];
    let mut b = [0.0, 0.0];
    assert_eq!(adam.lr(0), 0.1);
    adam.step(&mut [&mut a, &mut b], &[&[2.0, -1e-3, 0.0], &[7.0, -7.0]])
        .unwrap();
    // Bias-corrected first step: Δp = −lr · g/|g| (0 where g = 0).
    assert!(rel(a[0], 0.9) < 1e-12 && rel(a[1], 2.1) < 1e-12 && a[2] == 3.0);
    assert!(rel(b[0], -0.5) < 1e-12 && rel(b[1], 0.5) < 1e-12);
    assert_eq!(adam.steps(), 1);
    assert!(rel(adam.lr(0), 0.1 * 0.1f64.powf(1.0 / 9.0)) < 1e-12);
}

#[test]
fn adam_minimises_a_quadratic() {
    let target = [[0.3, -1.0, 2.0], [5.0, -4.0, 0.0]];
    let mut adam = Adam::new(
        AdamConfig::default(),
        groups(
            LrSchedule::exponential(0.1, 1e-3, 500),
            LrSchedule::exponential(0.2, 1e-3, 500),
        ),
    )
    .unwrap();
    let mut a = vec![0.0; 3];
    let mut b = vec![0.0; 2];
    for _ in 0..600 {
        let ga: Vec<f64> = a
            .iter()
            .zip(&target[0])
            .map(|(p, t)| 2.0 * (p - t))
            .collect();
        let gb: Vec<f64> = b
            .iter()
            .zip(&target[1])
            .map(|(p, t)| 2.0 * (p - t))
            .collect();
        adam.step(&mut [&mut a, &mut b], &[&ga, &gb]).unwrap();
    }
    for (p, t) in a
        .iter()
        .chain(&b)
        .zip(target[0].iter().chain(&target[1][..2]))
    {
        assert!((p - t).abs() < 1e-2, "{p} vs {t}");
    }
}

#[test]
fn bad_gradients_and_settings_are_errors_and_change_nothing() {
    let mut adam = Adam::new(
        AdamConfig::default(),
        groups(LrSchedule::constant(0.1), LrSchedule::constant(0.1)),
    )
    .unwrap();
    let mut a = [1.0, 2.0, 3.0];
    let mut b = [4.0, 5.0];
    let err = adam
        .step(&mut [&mut a, &mut b], &[&[1.0, 1.0, 1.0], &[0.0, f64::NAN]])
        .unwrap_err();
    assert!(matches!(err, FieldError::NotFinite { index: 1, .. }));
    assert!(err.to_string().contains("gradient of mlp"), "{err}");
    assert_eq!((a, b, adam.steps()), ([1.0, 2.0, 3.0], [4.0, 5.0], 0));
    let err = adam
        .step(&mut [&mut a, &mut b], &[&[1.0, 1.0], &[0.0, 0.0]])
        .unwrap_err();
    assert_eq!(
        err,
        FieldError::Length {
            field: "planes",
            expected: 3,
            got: 2
        }
    );
    assert!(adam.step(&mut [&mut a], &[&[1.0, 1.0, 1.0]]).is_err());
    assert_eq!((a, b, adam.steps()), ([1.0, 2.0, 3.0], [4.0, 5.0], 0));

    let bad_lr = groups(LrSchedule::constant(0.0), LrSchedule::constant(0.1));
    let err = Adam::new(AdamConfig::default(), bad_lr).unwrap_err();
    assert!(matches!(
        err,
        FieldError::Config {
            field: "planes",
            ..
        }
    ));
    let bad_steps = groups(
        LrSchedule::constant(0.1),
        LrSchedule::exponential(0.1, 0.01, 0),
    );
    assert!(Adam::new(AdamConfig::default(), bad_steps).is_err());
    let bad_beta = AdamConfig {
        beta2: 1.0,
        ..AdamConfig::default()
    };
    let ok = groups(LrSchedule::constant(0.1), LrSchedule::constant(0.1));
    assert!(matches!(
        Adam::new(bad_beta, ok).unwrap_err(),
        FieldError::Config { field: "beta2", .. }
    ));
}
