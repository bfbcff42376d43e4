use super::*;

const GOOD: &str = r#"{
  "name": "hannover-double-8",
  "scanners": {
    "left":  {"lever_arm_m": [-0.6,  0.35, 0.45], "boresight_deg": [0, 0, 0]},
    "right": {"lever_arm_m": [-0.6, -0.35, 0.45]}
  },
  "trajectories": [{"id": "p01", "uri": "trajectories/p01.csv"}, {"id": "p02", "uri": "./trajectories/p02.csv"}],
  "strips": [
    {"id": "p01-left", "trajectory": "p01", "scanner": "left", "uri": "strips/p01-left.laz"},
    {"id": "p02-right", "trajectory": "p02", "scanner": "right", "uri": "strips/p02-right.las"}
  ],
  "parameters": {"anchor_spacing_m": 1.0, "schedule": [{"grid_m": 0.1, "threshold_m": 0.3}]}
}"#;

fn with(edit: impl FnOnce(&mut Value)) -> String {
    let mut v: Value = serde_json::from_str(GOOD).unwrap();
    edit(&mut v);
    v.to_string()
}

fn problems(text: &str) -> Vec<ManifestProblem> {
    match parse_manifest(text) {
        Err(ManifestError::Invalid { problems, .. }) => problems,
        other => panic!("expected problems, got {other:?}"),
    }
}

fn has(problems: &[ManifestProblem], path: &str, needle: &str) -> bool {
    problems.iter().any(|p| p.path == path && p.message.contains(needle))
}

#[test]
fn good_manifest_parses_with_defaults() {
    let m = parse_manifest(GOOD).unwrap();
    assert_eq!(m.scanners["right"].boresight_deg, [0.0; 3]);
    assert_eq!(m.parameters.anchor_spacing_m, 1.0);
    assert_eq!(m.parameters.tile_size_m, 15.0);
    assert_eq!(m.strips[1].scanner, "right");
    // Serializing and parsing again is the identity (the simulator writes manifests).
    let again = parse_manifest(&serde_json::to_string(&m).unwrap()).unwrap();
    assert_eq!(again, m);
    let no_params = with(|v| {
        v.as_object_mut().unwrap().remove("parameters");
    });
    assert_eq!(parse_manifest(&no_params).unwrap().parameters, Parameters::default());
}

#[test]
fn unknown_fields_at_every_level() {
    let text = with(|v| {
        v["nmae"] = Value::from("x");
        v["parameters"]["anchor_spacing"] = Value::from(1.0);
        v["parameters"]["schedule"][0]["grid"] = Value::from(1.0);
        v["strips"][1]["scaner"] = Value::from("left");
        v["scanners"]["left"]["lever_arm"] = Value::from(1.0);
        v["trajectories"][0]["url"] = Value::from("x");
    });
    let p = problems(&text);
    assert!(has(&p, "$.nmae", "did you mean \"name\""), "{p:#?}");
    assert!(has(&p, "$.parameters.anchor_spacing", "did you mean \"anchor_spacing_m\""), "{p:#?}");
    assert!(has(&p, "$.parameters.schedule[0].grid", "unknown field"), "{p:#?}");
    assert!(has(&p, "$.strips[1].scaner", "did you mean \"scanner\""), "{p:#?}");
    assert!(has(&p, "$.scanners.left.lever_arm", "unknown field"), "{p:#?}");
    assert!(has(&p, "$.trajectories[0].url", "unknown field"), "{p:#?}");
    assert_eq!(p.len(), 6, "{p:#?}");
}

#[test]
fn duplicate_ids() {
    let text = with(|v| {
        v["trajectories"][1]["id"] = Value::from("p01");
        v["strips"][1]["id"] = Value::from("p01-left");
        v["strips"][1]["trajectory"] = Value::from("p01");
    });
    let p = problems(&text);
    assert!(has(&p, "$.trajectories[1].id", "duplicate trajectory id \"p01\" (also $.trajectories[0])"), "{p:#?}");
    assert!(has(&p, "$.strips[1].id", "duplicate strip id \"p01-left\" (also $.strips[0])"), "{p:#?}");
    assert_eq!(p.len(), 2, "{p:#?}");
}

#[test]
fn missing_trajectory_and_scanner() {
    let text = with(|v| {
        v["strips"][1]["trajectory"] = Value::from("p07");
        v["strips"][0]["scanner"] = Value::from("middle");
    });
    let p = problems(&text);
    assert!(
        has(
            &p,
            "$.strips[1].trajectory",
            "add a trajectory with id \"p07\" to $.trajectories or fix the strip's trajectory field"
        ),
        "{p:#?}"
    );
    assert!(has(&p, "$.strips[0].scanner", "scanner \"middle\" is not listed (known: left, right)"), "{p:#?}");
}

#[test]
fn unsafe_uris() {
    for (uri, needle) in [
        ("file:///etc/passwd", "scheme"),
        ("../x.las", "'..'"),
        ("/abs.las", "absolute"),
        ("s3://b/k", "scheme"),
        ("http://example.com/a.laz", "scheme"),
        ("C:/data/a.laz", "drive"),
        ("strips\\a.laz", "backslash"),
        ("", "empty"),
        ("a\0b.las", "control"),
        ("strips/../../x.las", "'..'"),
        ("strips//a.las", "empty path component"),
        (".", "does not name a file"),
    ] {
        let text = with(|v| v["strips"][0]["uri"] = Value::from(uri));
        let p = problems(&text);
        assert!(has(&p, "$.strips[0].uri", needle), "{uri:?}: {p:#?}");
        assert!(resolve_uri(Path::new("/m"), uri).is_err());
    }
    let text = with(|v| v["trajectories"][1]["uri"] = Value::from("/etc/passwd"));
    assert!(has(&problems(&text), "$.trajectories[1].uri", "absolute"));
    assert_eq!(resolve_uri(Path::new("/m"), "./strips/a.laz").unwrap(), Path::new("/m/strips/a.laz"));
    assert_eq!(resolve_uri(Path::new("m"), "a.laz").unwrap(), Path::new("m/a.laz"));
}

#[test]
fn malformed_json_has_line_and_column() {
    let p = problems("{\n  \"name\": \"x\",\n  \"strips\": [1,],\n}");
    assert_eq!(p.len(), 1);
    assert_eq!(p[0].path, "$");
    assert!(p[0].message.contains("malformed JSON at line 3, column"), "{}", p[0].message);
    // Out-of-range numbers cannot sneak in as infinities.
    let text = with(|v| v["scanners"]["left"]["lever_arm_m"][0] = Value::from(1.0)).replacen("[1.0,", "[1e999,", 1);
    assert!(problems(&text)[0].message.contains("malformed JSON"), "{text}");
}

#[test]
fn types_missing_fields_and_ids() {
    let text = with(|v| {
        v.as_object_mut().unwrap().remove("name");
        v["scanners"]["left"]["lever_arm_m"] = serde_json::json!([1, 2]);
        v["scanners"]["right"].as_object_mut().unwrap().remove("lever_arm_m");
        v["scanners"]["bad/name"] = serde_json::json!({"lever_arm_m": [0, 0, 0]});
        v["trajectories"][0]["id"] = Value::from(".hidden");
        v["trajectories"][1]["uri"] = Value::from(5);
        v["strips"][0].as_object_mut().unwrap().remove("uri");
        v["parameters"]["tile_size_m"] = Value::from("15");
        v["parameters"]["anderson_depth"] = Value::from(2.5);
        v["parameters"]["schedule"][0].as_object_mut().unwrap().remove("threshold_m");
    });
    let p = problems(&text);
    assert!(has(&p, "$.name", "missing required field \"name\""), "{p:#?}");
    assert!(has(&p, "$.scanners.left.lever_arm_m", "3 numbers"), "{p:#?}");
    assert!(has(&p, "$.scanners.right.lever_arm_m", "missing required field \"lever_arm_m\""), "{p:#?}");
    assert!(has(&p, "$.scanners[\"bad/name\"]", "not a safe file name"), "{p:#?}");
    assert!(has(&p, "$.trajectories[0].id", "not a safe file name"), "{p:#?}");
    assert!(has(&p, "$.trajectories[1].uri", "expected a string, found a number"), "{p:#?}");
    assert!(has(&p, "$.strips[0].uri", "missing required field \"uri\""), "{p:#?}");
    // The renamed trajectory is really gone, so the strip that used it is reported too.
    assert!(has(&p, "$.strips[0].trajectory", "trajectory \"p01\" is not listed"), "{p:#?}");
    assert!(has(&p, "$.parameters.tile_size_m", "expected a number, found a string"), "{p:#?}");
    assert!(has(&p, "$.parameters.schedule[0].threshold_m", "missing required field"), "{p:#?}");
    assert!(has(&p, "$.parameters.anderson_depth", "expected a whole number (0 or more), found 2.5"), "{p:#?}");
    assert_eq!(p.len(), 11, "{p:#?}");
    let negative = problems(&with(|v| v["parameters"]["anderson_depth"] = Value::from(-1)));
    assert!(has(&negative, "$.parameters.anderson_depth", "found -1"), "{negative:#?}");
    assert!(has(&problems("[]"), "$", "expected an object, found an array"));
    let long = "a".repeat(65);
    assert!(has(&problems(&with(|v| v["strips"][0]["id"] = Value::from(long))), "$.strips[0].id", "1–64"));
}

#[test]
fn absurd_numbers_and_names_are_refused_with_their_path() {
    let text = with(|v| {
        v["name"] = Value::from("a\u{0}b");
        v["scanners"]["left"]["lever_arm_m"][1] = Value::from(1e308);
        v["scanners"]["right"]["boresight_deg"] = serde_json::json!([0, -720, 0]);
        v["parameters"]["anchor_spacing_m"] = Value::from(1e-9);
        v["parameters"]["max_range_m"] = Value::from(1e300);
        v["parameters"]["schedule"][0]["threshold_m"] = Value::from(5e4);
    });
    let p = problems(&text);
    assert!(has(&p, "$.name", "control character"), "{p:#?}");
    assert!(has(&p, "$.scanners.left.lever_arm_m[1]", "out of range"), "{p:#?}");
    assert!(has(&p, "$.scanners.right.boresight_deg[1]", "out of range"), "{p:#?}");
    assert!(has(&p, "$.parameters.anchor_spacing_m", "too fine"), "{p:#?}");
    assert!(has(&p, "$.parameters.max_range_m", "out of range"), "{p:#?}");
    assert!(has(&p, "$.parameters.schedule[0].threshold_m", "out of range"), "{p:#?}");
    assert_eq!(p.len(), 6, "{p:#?}");
    let long = with(|v| v["name"] = Value::from("x".repeat(MAX_NAME_CHARS + 1)));
    assert!(has(&problems(&long), "$.name", "at most 200"));
    assert!(parse_manifest(GOOD).is_ok());
}

#[test]
fn empty_strips_and_parameter_ranges() {
    let text = with(|v| {
        v["strips"] = serde_json::json!([]);
        v["parameters"]["anchor_spacing_m"] = Value::from(-1.0);
        v["parameters"]["schedule"][0]["grid_m"] = Value::from(0.0);
    });
    let p = problems(&text);
    assert!(has(&p, "$.strips", "is empty"), "{p:#?}");
    assert!(has(&p, "$.parameters.anchor_spacing_m", "positive"), "{p:#?}");
    assert!(has(&p, "$.parameters.schedule[0].grid_m", "positive"), "{p:#?}");
    assert_eq!(p.len(), 3, "{p:#?}");
}

#[test]
fn ring_sources_parse_and_ring_image_needs_one() {
    use precimap_core::{NormalSource, RingSource};
    for (value, want) in [
        (serde_json::json!("user_data"), RingSource::UserData),
        (serde_json::json!("scanner_channel"), RingSource::ScannerChannel),
        (serde_json::json!({ "extra_bytes": "ring" }), RingSource::ExtraBytes("ring".into())),
    ] {
        let text = with(|v| v["parameters"]["ring"] = value.clone());
        assert_eq!(parse_manifest(&text).unwrap().parameters.ring, Some(want));
    }
    let text = with(|v| v["parameters"]["ring"] = Value::from("laser"));
    assert!(has(&problems(&text), "$.parameters", "unknown variant"), "{:#?}", problems(&text));
    let text = with(|v| v["parameters"]["normals"] = Value::from("ring_image"));
    assert!(has(&problems(&text), "$.parameters.normals", "parameters.ring"), "{:#?}", problems(&text));
    let text = with(|v| {
        v["parameters"]["normals"] = Value::from("ring_image");
        v["parameters"]["ring"] = Value::from("user_data");
    });
    assert_eq!(parse_manifest(&text).unwrap().parameters.normals, NormalSource::RingImage);
}

#[test]
fn all_problems_at_once_and_display_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("campaign.json");
    let text = with(|v| {
        v["extra"] = Value::from(1);
        v["parameters"]["bogus"] = Value::from(1);
        v["strips"][0]["uri"] = Value::from("../x.las");
        v["strips"][1]["trajectory"] = Value::from("p07");
        v["trajectories"][1]["id"] = Value::from("p01");
    });
    std::fs::write(&file, text).unwrap();
    let e = load_manifest(&file).unwrap_err();
    let ManifestError::Invalid { file: Some(f), problems } = &e else { panic!("{e:?}") };
    assert_eq!(f, &file);
    let paths: Vec<&str> = problems.iter().map(|p| p.path.as_str()).collect();
    for want in ["$.extra", "$.parameters.bogus", "$.strips[0].uri", "$.strips[1].trajectory", "$.trajectories[1].id"] {
        assert!(paths.contains(&want), "{want} missing from {paths:?}");
    }
    assert_eq!(problems.len(), 5, "{problems:#?}");
    let shown = e.to_string();
    assert_eq!(shown.lines().count(), 5, "{shown}");
    for line in shown.lines() {
        assert!(line.starts_with(&format!("{}: $", file.display())), "{line}");
    }
    let missing = load_manifest(&dir.path().join("none.json")).unwrap_err();
    assert!(matches!(missing, ManifestError::Io { .. }) && missing.to_string().contains("none.json"));
}

/// The calibration's options: any subset of its fields, kinds by name; an unknown field, an
/// unknown kind or a non-positive σ is refused with its path.
#[test]
fn calibration_options_are_checked_with_their_path() {
    let ok = with(|v| {
        v["parameters"]["calibration"] =
            serde_json::json!({"estimate": ["boresight", "range_offset"], "prior_lever_arm_m": 0.2});
    });
    let m = parse_manifest(&ok).unwrap();
    assert_eq!(m.parameters.calibration.estimate.len(), 2);
    assert_eq!(m.parameters.calibration.prior_lever_arm_m, 0.2);
    let p =
        problems(&with(|v| v["parameters"]["calibration"] = serde_json::json!({"estimate": ["boresight"], "tilt": 1})));
    assert!(has(&p, "$.parameters.calibration.tilt", "unknown field"), "{p:#?}");
    let p = problems(&with(|v| v["parameters"]["calibration"] = serde_json::json!({"estimate": ["scale"]})));
    assert!(has(&p, "$.parameters", "scale"), "{p:#?}");
    let p = problems(&with(|v| v["parameters"]["calibration"] = serde_json::json!({"tolerance_boresight_deg": 0})));
    assert!(has(&p, "$.parameters.calibration.tolerance_boresight_deg", "positive"), "{p:#?}");
}
