//! Spinning throws through `ingest → init → warmup → velocity` (generated, 48×48, 6 cameras, 5
//! frames in free flight).

mod generated;

use serde_json::Value;

use generated::{Run, generate};

/// A generated elastic body of `shape` and `extent` (m) thrown at `v0` (m/s) with `spin`
/// (rad/s), through the velocity stage (`model: rigid`, the draft's epochs); its
/// `velocity.json`.
fn spinning(shape: &str, extent: &str, v0: &str, spin: &str) -> Value {
    let dir = tempfile::tempdir().unwrap();
    generate(
        "scene",
        &dir.path().join("scene"),
        &[
            "--family",
            "elastic",
            "--youngs-modulus",
            "5e5",
            "--poisson-ratio",
            "0.3",
            "--shape",
            shape,
            "--extent",
            extent,
            "--drop-height",
            "0.3",
            "--v0",
            v0,
            "--spin",
            spin,
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
        "name: spinning\nscene:\n  dataset: pacnerf\n  path: scene\n  test_views: [5]\n  \
         material: elastic\npreset: draft\nstages:\n  ingest: {matte: plate}\n  \
         init: {source: visual_hull}\n  warmup: {frames: [0], epochs: 30}\n  \
         velocity: {model: rigid}\n",
        shape,
    );
    run.json("velocity", "velocity.json")
}

fn vec3(v: &Value, key: &str) -> [f64; 3] {
    serde_json::from_value(v[key].clone()).unwrap()
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt()
}

/// A tumbling bar (0.4 × 0.1 × 0.2 m, spin [3, 1, 6] rad/s): the velocity stage starts its
/// descent from the turn of the masks' hulls (`track::fit_angular_velocity`) and learns the
/// spin: measured from a start of [2.74, 1.85, 5.22] rad/s to [2.78, 0.96, 5.78] (the scene
/// drawn as the body, 2026-11-30). On the scene drawn as spheres (2026-11-29) it learned
/// [2.64, 1.00, 5.66], as with 40 epochs, and from rest (`init: zero`) the draft's epochs found
/// only the spin about y: [−0.04, 0.00, 5.56], 3.1 rad/s off (on the 100×100 version the
/// hull's linear start but no spin left 0.76 of the 3 rad/s about the long axis).
#[test]
fn a_tumbling_throws_spin_is_learned_from_the_hulls_turn() {
    let v = spinning("bar", "0.4,0.1,0.2", "0.5,0.6,-0.2", "3,1,6");
    let (start, learned) = (
        vec3(&v, "start_angular_velocity"),
        vec3(&v, "angular_velocity"),
    );
    println!(
        "spin: start {start:?}, learned {learned:?}; v0 {:?}",
        vec3(&v, "initial_velocity")
    );
    // The hulls' turn is a start, not an answer: within a third of the spin's 6.8 rad/s.
    let truth = [3.0, 1.0, 6.0];
    assert!(distance(start, truth) < 2.3, "the start turns at {start:?}");
    assert!(distance(learned, truth) < 0.8, "learned spin {learned:?}");
    assert!(
        distance(vec3(&v, "linear_velocity"), [0.5, 0.6, -0.2]) < 0.1,
        "{}",
        v["linear_velocity"]
    );
}

/// A ball flattened along y (0.3 × 0.2 × 0.3 m) spinning at [0, 8, 2] rad/s, mostly about its
/// axis of symmetry: its silhouette does not show that turn (its hulls give no start), only
/// its texture does. The spin probes (`velocity.probe_spin`) start the descent at [0.00, 8.38,
/// 2.09] and it learns [0.06, 7.39, 1.93] (measured on the scene drawn as the body,
/// 2026-11-30); on the scene drawn as spheres they started it at [0.71, 5.62, 1.21], and
/// without them it stopped at [0.57, 1.76, 1.21] (with E = 3e5 Pa; the loss of a free flight
/// does not depend on it).
#[test]
fn a_balls_spin_about_its_axis_is_found_by_the_probes() {
    let v = spinning("ball", "0.3,0.2,0.3", "0.3,0,0.3", "0,8,2");
    let (start, learned) = (
        vec3(&v, "start_angular_velocity"),
        vec3(&v, "angular_velocity"),
    );
    println!("spin: start {start:?}, learned {learned:?}");
    assert!(
        distance(learned, [0.0, 8.0, 2.0]) < 1.5,
        "learned spin {learned:?}"
    );
    assert!(distance(vec3(&v, "linear_velocity"), [0.3, 0.0, 0.3]) < 0.1);
}
