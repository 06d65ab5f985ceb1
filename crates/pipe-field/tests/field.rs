//! Behaviour of a field: continuity across plane cell edges, the constant initialisation,
//! clamping outside the box (never NaN), typed errors for bad input, deterministic
//! initialisation, bit-identical gradients with 1 and 2 threads, and the weights round trip.

use pipe_field::{
    Activation, CHUNK, Combine, Domain, Field, FieldConfig, FieldError, FieldWeights,
};

struct Lcg(u64);
impl Lcg {
    fn uniform(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64) / (1u64 << 53) as f64
    }
}

fn domain() -> Domain {
    Domain::new([-1.0, 0.0, -0.5], [1.0, 0.8, 0.5]).unwrap()
}

fn random_points(n: usize, seed: u64, d: &Domain) -> Vec<[f64; 3]> {
    let mut r = Lcg(seed);
    let (lo, hi) = (d.min(), d.max());
    (0..n)
        .map(|_| std::array::from_fn(|a| lo[a] + (hi[a] - lo[a]) * r.uniform()))
        .collect()
}

/// Bound on |y(x + e) − y(x − e)| across every interior cell edge of every axis, as a
/// multiple of e: a jump at an edge (e.g. sampling with the wrong cell's weights) would make
/// the ratio ~1/e, a continuous field keeps it at the field's slope.
#[test]
fn field_is_continuous_across_plane_cell_edges() {
    let d = domain();
    for combine in [Combine::Sum, Combine::Concat] {
        let config = FieldConfig {
            resolution: 6,
            combine,
            plane_init: 1.0,
            ..FieldConfig::material(2)
        };
        let field = Field::new(&config, d, 21).unwrap();
        let (lo, hi) = (d.min(), d.max());
        let e = 1e-9;
        let mut worst: f64 = 0.0;
        let mut across_cell: f64 = 0.0;
        for base in random_points(8, 3, &d) {
            for a in 0..3 {
                for edge in 1..config.resolution - 1 {
                    let t = lo[a] + (hi[a] - lo[a]) * edge as f64 / (config.resolution - 1) as f64;
                    let (mut l, mut r) = (base, base);
                    l[a] = t - e;
                    r[a] = t + e;
                    let y = field.forward(&[l, r]).unwrap();
                    for k in 0..2 {
                        worst = worst.max((y[k] - y[2 + k]).abs() / (2.0 * e));
                    }
                    // The same points half a cell apart: the field does vary.
                    let mut far = base;
                    far[a] = t + 0.5 * (hi[a] - lo[a]) / (config.resolution - 1) as f64;
                    let z = field.forward(&[far]).unwrap();
                    across_cell = across_cell.max((z[0] - y[0]).abs());
                }
            }
        }
        // Slopes of this field are below 10 per metre (7.5 measured); a jump of even 1e-6 at an
        // edge would give 500 (swapping two corner weights gives 8.5e8).
        assert!(
            worst < 100.0,
            "{combine:?}: |Δy|/Δx = {worst} across an edge"
        );
        assert!(
            across_cell > 1e-3,
            "{combine:?}: field is flat ({across_cell})"
        );
    }
}

#[test]
fn constant_initialisation_outputs_exactly_the_given_vector() {
    let value = [5.75, -0.3];
    for activation in [Activation::Relu, Activation::Softplus] {
        let config = FieldConfig {
            activation,
            ..FieldConfig::material(2)
        };
        let field = Field::with_constant_output(&config, domain(), 9, &value).unwrap();
        let mut x = random_points(100, 4, &domain());
        x.push([10.0, -10.0, f64::INFINITY]);
        let y = field.forward(&x).unwrap();
        for row in y.chunks_exact(2) {
            assert_eq!(row, value);
        }
        // The output layer gets a gradient at once; planes and hidden layers after it moves.
        let g = field.backward(&x, &vec![1.0; y.len()]).unwrap();
        let last = field.mlp().layer_ranges().last().unwrap();
        assert!(g.mlp[last.2].iter().any(|v| *v != 0.0));
        assert!(g.mlp[last.3].iter().all(|v| *v == x.len() as f64));
    }
}

#[test]
fn points_outside_the_box_are_clamped_and_never_nan() {
    let d = domain();
    let field = Field::new(&FieldConfig::material(2), d, 2).unwrap();
    let far = [
        [1e300, -1e300, 3.0],
        [f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY],
        [-5.0, 0.4, 0.0],
        [f64::MAX, f64::MIN, f64::MIN_POSITIVE],
    ];
    let clamped: Vec<[f64; 3]> = far
        .iter()
        .map(|p| std::array::from_fn(|a| p[a].clamp(d.min()[a], d.max()[a])))
        .collect();
    let y = field.forward(&far).unwrap();
    assert!(y.iter().all(|v| v.is_finite()));
    assert_eq!(y, field.forward(&clamped).unwrap());
    let (g, dx) = field
        .backward_with_points(&far, &vec![1.0; y.len()])
        .unwrap();
    assert!(g.to_flat().iter().all(|v| v.is_finite()));
    assert!(dx.iter().flatten().all(|v| v.is_finite()));
    // Fully clamped points have no position gradient; point 2 only along y and z.
    assert_eq!(dx[0], [0.0, 0.0, 0.0]);
    assert_eq!(dx[1], [0.0, 0.0, 0.0]);
    assert_eq!(dx[2][0], 0.0);
}

#[test]
fn nan_coordinates_are_errors_naming_the_point_and_axis() {
    let field = Field::new(&FieldConfig::velocity(3), domain(), 2).unwrap();
    let x = [[0.0, 0.1, 0.0], [0.0, f64::NAN, 0.0]];
    let err = field.forward(&x).unwrap_err();
    assert_eq!(
        err,
        FieldError::PointNaN {
            field: "points",
            index: 1,
            axis: 'y'
        }
    );
    assert_eq!(err.to_string(), "`points`[1].y is NaN");
    assert!(field.backward(&x, &[0.0; 6]).is_err());
}

#[test]
fn a_zero_extent_axis_is_an_error_naming_the_axis() {
    let err = Domain::new([0.0, 0.0, 0.0], [1.0, 1.0, 0.0]).unwrap_err();
    assert!(matches!(err, FieldError::DomainExtent { axis: 'z', .. }));
    assert!(err.to_string().contains("axis z"), "{err}");
    let err = Domain::new([0.0, 2.0, 0.0], [1.0, 1.0, 1.0]).unwrap_err();
    assert!(matches!(err, FieldError::DomainExtent { axis: 'y', .. }));
    let err = Domain::new([f64::NAN, 0.0, 0.0], [1.0, 1.0, 1.0]).unwrap_err();
    assert!(matches!(
        err,
        FieldError::DomainNotFinite {
            field: "min",
            axis: 'x',
            ..
        }
    ));
    // The box of a flat point set is flat unless a margin is given.
    let flat = [[0.0, 0.5, 0.0], [1.0, 0.5, 2.0]];
    let err = Domain::around(&flat, 0.0).unwrap_err();
    assert!(matches!(err, FieldError::DomainExtent { axis: 'y', .. }));
    let d = Domain::around(&flat, 0.1).unwrap();
    assert_eq!(d.min(), [-0.1, 0.4, -0.1]);
    assert_eq!(d.max(), [1.1, 0.6, 2.1]);
    assert!(Domain::around(&[], 0.1).is_err());
}

#[test]
fn length_mismatches_and_bad_values_are_errors() {
    let config = FieldConfig::material(2);
    let mut field = Field::new(&config, domain(), 2).unwrap();
    let x = random_points(5, 1, &domain());
    let err = field.backward(&x, &[0.0; 9]).unwrap_err();
    assert_eq!(
        err,
        FieldError::Length {
            field: "d_outputs",
            expected: 10,
            got: 9
        }
    );
    let mut d = vec![0.0; 10];
    d[7] = f64::NAN;
    assert!(matches!(
        field.backward(&x, &d).unwrap_err(),
        FieldError::NotFinite { index: 7, .. }
    ));
    assert!(matches!(
        Field::with_constant_output(&config, domain(), 1, &[1.0]).unwrap_err(),
        FieldError::Length {
            field: "value",
            expected: 2,
            got: 1
        }
    ));
    let before = field.clone();
    let n = field.param_count();
    assert!(matches!(
        field.set_flat(&vec![0.0; n + 1]).unwrap_err(),
        FieldError::Length { .. }
    ));
    let mut bad = field.to_flat();
    bad[3] = f64::INFINITY;
    assert!(field.set_flat(&bad).is_err());
    assert_eq!(field, before);
    // Weights that overflow the output are caught, not passed on as inf/NaN.
    let mut huge = field.clone();
    huge.params_mut().0.fill(f64::MAX);
    assert!(matches!(
        huge.forward(&x).unwrap_err(),
        FieldError::NotFinite { .. }
    ));
    assert!(huge.backward(&x, &[1.0; 10]).is_err());
    let mut g = pipe_field::FieldGradient {
        planes: vec![0.0; 3],
        mlp: vec![],
    };
    assert!(field.tv_backward(&mut g).is_err());
    for bad in [
        FieldConfig {
            resolution: 1,
            ..config
        },
        FieldConfig {
            channels: 0,
            ..config
        },
        FieldConfig {
            outputs: 0,
            ..config
        },
        FieldConfig {
            hidden: 0,
            ..config
        },
        FieldConfig {
            tv_weight: f64::NAN,
            ..config
        },
    ] {
        assert!(matches!(
            Field::new(&bad, domain(), 0).unwrap_err(),
            FieldError::Config { .. }
        ));
    }
    // No hidden layer is allowed (a linear read-out of the features).
    let linear = FieldConfig {
        layers: 0,
        hidden: 0,
        ..config
    };
    assert!(Field::new(&linear, domain(), 0).is_ok());
}

#[test]
fn initialisation_is_deterministic_from_the_seed() {
    let config = FieldConfig::material(2);
    let a = Field::new(&config, domain(), 17).unwrap();
    let b = Field::new(&config, domain(), 17).unwrap();
    let c = Field::new(&config, domain(), 18).unwrap();
    // 3·24²·16 plane features + (16·64 + 64) + (64·64 + 64) + (64·2 + 2) MLP parameters.
    assert_eq!(a.param_count(), 33_026);
    assert_eq!(a.to_flat(), b.to_flat());
    assert_ne!(a.to_flat(), c.to_flat());
    let planes = a.triplane().values();
    assert!(planes.iter().all(|v| v.abs() <= config.plane_init));
    assert!(planes.iter().any(|v| v.abs() > 0.9 * config.plane_init));
}

#[test]
fn gradients_are_bit_identical_with_1_and_2_threads() {
    let d = domain();
    // Several chunks, the last one partial.
    let n = 5 * CHUNK + 37;
    let x = random_points(n, 8, &d);
    for combine in [Combine::Sum, Combine::Concat] {
        let config = FieldConfig {
            combine,
            ..FieldConfig::material(2)
        };
        let field = Field::new(&config, d, 5).unwrap();
        let mut r = Lcg(2);
        let g: Vec<f64> = (0..2 * n).map(|_| r.uniform() - 0.5).collect();
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    let y = field.forward(&x).unwrap();
                    let (grad, dx) = field.backward_with_points(&x, &g).unwrap();
                    (y, grad, dx)
                })
        };
        let one = run(1);
        let two = run(2);
        let bits = |v: &[f64]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&one.0), bits(&two.0));
        assert_eq!(bits(&one.1.to_flat()), bits(&two.1.to_flat()));
        assert_eq!(one.2, two.2);
        assert!(one.1.planes.iter().any(|v| *v != 0.0));
    }
}

#[test]
fn weights_round_trip_through_serde_and_reject_bad_tensors() {
    let config = FieldConfig {
        combine: Combine::Concat,
        activation: Activation::Softplus,
        ..FieldConfig::velocity(3)
    };
    let field = Field::new(&config, domain(), 12).unwrap();
    let w = field.weights();
    let names: Vec<&str> = w.tensors.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "plane.xy",
            "plane.xz",
            "plane.yz",
            "mlp.0.weight",
            "mlp.0.bias",
            "mlp.1.weight",
            "mlp.1.bias",
            "mlp.2.weight",
            "mlp.2.bias"
        ]
    );
    assert_eq!(w.tensors[0].shape, [8, 8, 16]);
    assert_eq!(w.tensors[3].shape, [48, 64]);
    assert_eq!(w.tensors[8].shape, [3]);
    let json = serde_json::to_string(&w).unwrap();
    let back: FieldWeights = serde_json::from_str(&json).unwrap();
    let rebuilt = Field::from_weights(&back).unwrap();
    assert_eq!(rebuilt, field);
    let x = random_points(50, 6, &domain());
    assert_eq!(rebuilt.forward(&x).unwrap(), field.forward(&x).unwrap());

    let mut bad = w.clone();
    bad.tensors[4].values.pop();
    let err = Field::from_weights(&bad).unwrap_err();
    assert!(err.to_string().contains("mlp.0.bias"), "{err}");
    let mut bad = w.clone();
    bad.tensors.swap(0, 1);
    assert!(matches!(
        Field::from_weights(&bad).unwrap_err(),
        FieldError::Weights { .. }
    ));
    let mut bad = w.clone();
    bad.tensors[1].values[0] = f64::NAN;
    let err = Field::from_weights(&bad).unwrap_err();
    assert!(err.to_string().contains("plane.xz"), "{err}");
    let mut bad = w;
    bad.domain_max[0] = bad.domain_min[0];
    assert!(matches!(
        Field::from_weights(&bad).unwrap_err(),
        FieldError::DomainExtent { axis: 'x', .. }
    ));
}
