//! A tumbling throw (a generated elastic bar spinning at [3, 1, 6] rad/s, 48×48, 6 cameras, 5
//! frames in free flight) through `ingest → init → warmup → velocity`: the velocity stage
//! starts its descent from the turn of the masks' hulls (`track::fit_angular_velocity`) and
//! learns the spin: measured [2.65, 0.99, 5.67] rad/s, the same with 40 epochs (what 48 pixels
//! resolve), from the hulls' [4.04, 2.10, 4.96]. From rest (`init: zero`) the draft's epochs
//! find only the spin about y: [−0.04, 0.00, 5.56], 3.1 rad/s off (on the 100×100 version the
//! hull's linear start but no spin left 0.76 of the 3 rad/s about the long axis).

mod generated;

use generated::{Run, generate};

#[test]
fn a_tumbling_throws_spin_is_learned_from_the_hulls_turn() {
    let dir = tempfile::tempdir().unwrap();
    generate(
        &dir.path().join("scene"),
        &[
            "--family",
            "elastic",
            "--youngs-modulus",
            "5e5",
            "--poisson-ratio",
            "0.3",
            "--shape",
            "bar",
            "--extent",
            "0.4,0.1,0.2",
            "--drop-height",
            "0.3",
            "--v0",
            "0.5,0.6,-0.2",
            "--spin",
            "3,1,6",
            "--size",
            "48",
            "--frames",
            "5",
            "--views",
            "6",
            "--spacing",
            "0.025",
            "--supersample",
            "2",
        ],
    );
    let run = Run::new(
        dir.path(),
        "name: tumbling\nscene:\n  dataset: pacnerf\n  path: scene\n  test_views: [5]\n  \
         material: elastic\npreset: draft\nstages:\n  ingest: {matte: plate}\n  \
         init: {source: visual_hull}\n  warmup: {frames: [0], epochs: 30}\n  \
         velocity: {model: rigid}\n",
        "tumbling",
    );
    let v = run.json("velocity", "velocity.json");
    let vec3 = |key: &str| -> [f64; 3] { serde_json::from_value(v[key].clone()).unwrap() };
    let err = |a: [f64; 3], b: [f64; 3]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f64>()
            .sqrt()
    };
    let (start, learned) = (vec3("start_angular_velocity"), vec3("angular_velocity"));
    println!(
        "spin: hulls {start:?}, learned {learned:?}; v0 {:?}",
        vec3("initial_velocity")
    );
    // The hulls' turn is a start, not an answer: within a third of the spin's 6.8 rad/s.
    let truth = [3.0, 1.0, 6.0];
    assert!(err(start, truth) < 2.3, "the hulls turn at {start:?}");
    assert!(err(learned, truth) < 0.8, "learned spin {learned:?}");
    assert!(
        err(vec3("linear_velocity"), [0.5, 0.6, -0.2]) < 0.1,
        "{}",
        v["linear_velocity"]
    );
}
