//! Every way a pipeline file can be wrong gets a precise message: file, line and column, the
//! bad key or value, and for typos the nearest valid key. Also checks preset and `--set`
//! precedence (defaults < preset < file < --set) and that the JSON Schema in `schemas/` is the
//! one the code generates.

use std::path::Path;

use pipe::pipeline::graph::Graph;
use pipe::pipeline::spec::{self, Overrides, Preset};

use crate::support::registry;

fn parse(text: &str) -> Result<spec::Pipeline, spec::SpecError> {
    spec::parse(
        Path::new("pipelines/t.yaml"),
        text,
        &registry(),
        &Overrides::default(),
    )
}

fn err(text: &str) -> String {
    let e = parse(text).expect_err("should fail");
    e.to_string()
}

const HEAD: &str = "name: t\nscene:\n  dataset: pacnerf\n  path: .\n";

#[test]
fn unknown_key_names_file_line_column_and_the_nearest_key() {
    let e = err(&format!(
        "{HEAD}stages:\n  source: {{value: 1}}\n  double:\n    factr: 3\n"
    ));
    assert_eq!(
        e,
        "pipelines/t.yaml: unknown key `factr` in stages.double at line 8:5; did you mean `factor`?"
    );
}

#[test]
fn unknown_top_level_key() {
    let e = err(&format!("{HEAD}stagez: {{}}\n"));
    assert!(
        e.contains("unknown key `stagez` at the top level at line 5:1; did you mean `stages`?"),
        "{e}"
    );
}

#[test]
fn unknown_scene_key() {
    let e = err("name: t\nscene:\n  dataset: pacnerf\n  pth: .\nstages: {source: {value: 1}}\n");
    assert!(
        e.contains("unknown key `pth` in scene at line 4:3; did you mean `path`?"),
        "{e}"
    );
}

#[test]
fn wrong_type_names_the_value_and_line() {
    let e = err(&format!("{HEAD}stages:\n  source:\n    value: lots\n"));
    assert!(
        e.contains("stages.source.value: invalid type: string \"lots\""),
        "{e}"
    );
    assert!(e.contains("at line 7:12"), "{e}");
}

#[test]
fn malformed_yaml_has_a_position() {
    let e = err(&format!("{HEAD}stages:\n  source: {{value: 1\n"));
    assert!(
        e.starts_with("pipelines/t.yaml: ") && e.contains(" at line "),
        "{e}"
    );
}

#[test]
fn unknown_stage_suggests_the_nearest() {
    let e = err(&format!("{HEAD}stages:\n  sorce: {{value: 1}}\n"));
    assert!(
        e.contains("unknown stage `sorce` in stages at line 6:3; did you mean `source`?"),
        "{e}"
    );
}

#[test]
fn missing_required_parts() {
    assert!(err("name: t\nstages: {source: {value: 1}}\n").contains("missing key `scene`"));
    let e = err(&format!("{HEAD}stages:\n  source: {{}}\n"));
    assert!(e.contains("missing key `value` in stages.source"), "{e}");
    assert!(err(&format!("{HEAD}stages: {{}}\n")).contains("non-empty mapping"));
    assert!(err("- just\n- a list\n").contains("a pipeline file is a mapping"));
}

#[test]
fn cycles_and_bad_needs_are_reported() {
    let text = format!(
        "{HEAD}stages:\n  source: {{value: 1, needs: [sum]}}\n  double: {{}}\n  sum: {{needs: [double]}}\n"
    );
    let p = parse(&text).unwrap();
    let e = Graph::build(&p, &registry()).unwrap_err().to_string();
    assert!(
        e.contains("the stages form a cycle: source -> double -> sum -> source"),
        "{e}"
    );
    let text = format!("{HEAD}stages:\n  source: {{value: 1}}\n  double: {{needs: [sorce]}}\n");
    let p = parse(&text).unwrap();
    let e = Graph::build(&p, &registry()).unwrap_err().to_string();
    assert!(
        e.contains("needs `sorce`, which is not a stage of this pipeline")
            && e.contains("did you mean `source`?"),
        "{e}"
    );
}

#[test]
fn precedence_is_defaults_preset_file_then_set() {
    let text = format!(
        "{HEAD}preset: draft\nstages:\n  source: {{value: 1}}\n  double: {{}}\n  sum: {{}}\n"
    );
    let p = parse(&text).unwrap();
    assert_eq!(p.preset, Preset::Draft);
    assert_eq!(
        p.stage("double").unwrap().params["factor"],
        2,
        "draft preset sets factor 2"
    );
    assert_eq!(p.stage("sum").unwrap().params["factor"], 1, "serde default");
    let std = spec::parse(
        Path::new("t.yaml"),
        &text,
        &registry(),
        &Overrides {
            preset: Some(Preset::Standard),
            sets: vec![],
        },
    )
    .unwrap();
    assert_eq!(
        std.stage("double").unwrap().params["factor"],
        1,
        "--preset overrides the file's"
    );
    let text2 = text.replace("double: {}", "double: {factor: 7}");
    let p = parse(&text2).unwrap();
    assert_eq!(
        p.stage("double").unwrap().params["factor"],
        7,
        "file beats preset"
    );
    let p = spec::parse(
        Path::new("t.yaml"),
        &text2,
        &registry(),
        &Overrides {
            preset: None,
            sets: vec!["double.factor=9".into(), "scene.test_views=[3, 4]".into()],
        },
    )
    .unwrap();
    assert_eq!(
        p.stage("double").unwrap().params["factor"],
        9,
        "--set beats the file"
    );
    assert_eq!(p.scene.test_views, vec![3, 4]);
}

#[test]
fn bad_overrides_are_precise() {
    let text = format!("{HEAD}stages:\n  source: {{value: 1}}\n  double: {{}}\n");
    let set = |s: &str| {
        spec::parse(
            Path::new("t.yaml"),
            &text,
            &registry(),
            &Overrides {
                preset: None,
                sets: vec![s.into()],
            },
        )
        .unwrap_err()
        .to_string()
    };
    assert!(set("double.factor").contains("missing `=`"));
    assert!(set("double=3").contains("the key must be stage.key"));
    let e = set("dubble.factor=3");
    assert!(
        e.contains("no stage `dubble`") && e.contains("did you mean `double`?"),
        "{e}"
    );
    let e = set("double.factr=3");
    assert!(
        e.contains("unknown key `factr` in stages.double (from --set double.factr=3)"),
        "{e}"
    );
    assert!(e.contains("did you mean `factor`?"), "{e}");
    let e = set("double.factor=abc");
    assert!(
        e.contains("invalid type") && e.contains("from --set double.factor=abc"),
        "{e}"
    );
}

#[test]
fn relative_scene_path_is_anchored_at_the_file_or_the_command_line() {
    let p = spec::parse(
        Path::new("dir/sub/p.yaml"),
        &format!("{HEAD}stages: {{source: {{value: 1}}}}\n"),
        &registry(),
        &Overrides::default(),
    )
    .unwrap();
    assert_eq!(p.scene.path, Path::new("dir/sub/."));
    // A path typed on the command line is relative to the current directory instead.
    let p = spec::parse(
        Path::new("dir/sub/p.yaml"),
        &format!("{HEAD}stages: {{source: {{value: 1}}}}\n"),
        &registry(),
        &Overrides {
            preset: None,
            sets: vec!["scene.path=data/scene".into()],
        },
    )
    .unwrap();
    assert_eq!(p.scene.path, Path::new("data/scene"));
}

#[test]
fn committed_pipeline_schema_matches_the_code() {
    let generated = spec::json_schema(&pipe::stages::builtin());
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("schemas/pipeline.schema.json");
    let text = serde_json::to_string_pretty(&generated).unwrap() + "\n";
    if std::env::var_os("PIPE_WRITE_SCHEMAS").is_some() {
        std::fs::write(&path, &text).unwrap();
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == text,
        "schemas/pipeline.schema.json is out of date; regenerate with PIPE_WRITE_SCHEMAS=1 cargo test -p pipe --test cli schema"
    );
    // Every built-in stage and its keys appear.
    for stage in pipe::stages::builtin().iter() {
        assert!(generated["properties"]["stages"]["properties"][stage.kind()].is_object());
    }
    assert_eq!(
        generated["properties"]["stages"]["properties"]["ingest"]["properties"]["matte"]["$ref"],
        "#/$defs/MatteMode"
    );
}

#[test]
fn shipped_pipeline_files_parse_with_the_builtin_stages() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines");
    let mut seen = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "yaml") {
            let text = std::fs::read_to_string(&path).unwrap();
            let p = spec::parse(
                &path,
                &text,
                &pipe::stages::builtin(),
                &Overrides::default(),
            )
            .unwrap_or_else(|e| panic!("{e}"));
            let kinds: Vec<&str> = p.stages.iter().map(|s| s.kind.as_str()).collect();
            // From the images to a scored, learned scene; a PhysDreamer scene's Gaussians come
            // trained (its pipelines edit them).
            let learned: &[&str] = match p.scene.dataset {
                spec::DatasetKind::Pacnerf => &[
                    "ingest", "init", "warmup", "velocity", "material", "evaluate",
                ],
                spec::DatasetKind::Physdreamer => &["ingest", "init"],
            };
            assert_eq!(kinds[..learned.len()], *learned, "{}", path.display());
            // Then edits of the learned scene, if any.
            assert!(
                kinds[learned.len()..].iter().all(|k| *k == "edit"),
                "{}: {kinds:?}",
                path.display()
            );
            seen += 1;
        }
    }
    assert!(seen >= 2, "pipelines/*.yaml");
}

/// The two-material bar's pipeline exists to show a material field: it must not resolve to the
/// draft preset's default `model: global` (it did, silently, until the file set `auto`).
#[test]
fn the_two_material_pipeline_fits_a_field() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines/two-material-bar.yaml");
    let text = std::fs::read_to_string(&path).unwrap();
    let p = spec::parse(
        &path,
        &text,
        &pipe::stages::builtin(),
        &Overrides::default(),
    )
    .unwrap();
    let material = p.stages.iter().find(|s| s.kind == "material").unwrap();
    assert_eq!(material.params["model"], "auto", "{}", material.params);
}

#[test]
fn a_sweep_block_gives_axes_in_file_order_and_over_replaces_its_key() {
    let p = parse(&format!(
        "{HEAD}stages:\n  source: {{value: 1}}\nsweep:\n  source.value: [3, 1, 2]\n  preset: [draft, standard]\n  source.list: [[1, 2], [3]]\n"
    ))
    .unwrap();
    let axes: Vec<(String, Vec<String>)> = p
        .sweep
        .iter()
        .map(|a| (a.key.clone(), a.values.clone()))
        .collect();
    assert_eq!(
        axes,
        [
            (
                "source.value".to_string(),
                vec!["3".to_string(), "1".into(), "2".into()]
            ),
            (
                "preset".to_string(),
                vec!["draft".to_string(), "standard".into()]
            ),
            (
                "source.list".to_string(),
                vec!["[1,2]".to_string(), "[3]".into()]
            ),
        ]
    );
    // `pipe sweep --over` replaces the file's axis of the same key and appends new ones.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("t.yaml");
    std::fs::write(
        &file,
        format!("{HEAD}stages:\n  source: {{value: 1}}\nsweep:\n  source.value: [3, 1]\n  preset: [draft, standard]\n"),
    )
    .unwrap();
    let over = [
        pipe::sweep::Axis::parse("preset=paper").unwrap(),
        pipe::sweep::Axis::parse("source.factor=2,4").unwrap(),
    ];
    let merged = pipe::sweep::axes(&file, &registry(), &Overrides::default(), &over).unwrap();
    let keys: Vec<(&str, usize)> = merged
        .iter()
        .map(|a| (a.key.as_str(), a.values.len()))
        .collect();
    assert_eq!(
        keys,
        [("source.value", 2), ("preset", 1), ("source.factor", 2)]
    );
    // Without a block and without --over there is nothing to sweep.
    std::fs::write(&file, format!("{HEAD}stages:\n  source: {{value: 1}}\n")).unwrap();
    let e = pipe::sweep::axes(&file, &registry(), &Overrides::default(), &[]).unwrap_err();
    assert!(e.to_string().contains("nothing to sweep"), "{e}");
}

#[test]
fn a_bad_sweep_block_names_the_key() {
    let e = err(&format!(
        "{HEAD}stages:\n  source: {{value: 1}}\nsweep:\n  source.value: 3\n"
    ));
    assert!(
        e.contains("`sweep.source.value` must be a list of values") && e.contains("line 8"),
        "{e}"
    );
    let e = err(&format!(
        "{HEAD}stages:\n  source: {{value: 1}}\nsweep:\n  preset: [fast]\n"
    ));
    assert!(e.contains("unknown preset `fast`"), "{e}");
    let e = err(&format!(
        "{HEAD}stages:\n  source: {{value: 1}}\nsweep: [1, 2]\n"
    ));
    assert!(e.contains("`sweep` must map"), "{e}");
}
