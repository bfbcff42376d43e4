//! Campaign manifest (README, "A manifest"): which trajectories and strips form a campaign, the scanners'
//! mounting, and optional parameter overrides.
//!
//! Validation walks the JSON value before deserializing so that a user sees *every* problem at
//! once, each with its JSON path and what to do about it, instead of fixing them one serde error
//! at a time.

use precimap_core::Parameters;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};
use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::path::{Path, PathBuf};

mod control;
mod field;
pub use control::{ControlSpec, ControlTargetSpec, Sigma, MAX_CONTROL_SIGMA_M, MAX_CONTROL_TARGETS};
pub use field::{CrsSpec, TrajectoryFormat, MAX_GPS_WEEK};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub name: String,
    /// The processing CRS and local frame; absent for campaigns in a local metric frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crs: Option<CrsSpec>,
    /// The GPS week of files that count GPS week seconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gps_week: Option<u32>,
    /// Scanner name → mounting on the vehicle.
    pub scanners: BTreeMap<String, ScannerSpec>,
    pub trajectories: Vec<TrajectoryRef>,
    pub strips: Vec<StripRef>,
    #[serde(default)]
    pub parameters: Parameters,
    /// Surveyed control and check targets.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub control: Option<ControlSpec>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScannerSpec {
    /// Scan head position in the body frame (x forward, y left, z up), metres.
    pub lever_arm_m: [f64; 3],
    /// Nominal mounting rotation roll, pitch, yaw in degrees.
    #[serde(default)]
    pub boresight_deg: [f64; 3],
}

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrajectoryRef {
    pub id: String,
    /// Relative to the manifest's folder (see [`resolve_uri`]).
    pub uri: String,
    #[serde(default, skip_serializing_if = "TrajectoryFormat::is_csv")]
    pub format: TrajectoryFormat,
    /// EPSG code of the file's coordinates: for SBET the geographic CRS (4979 when absent), for
    /// CSV and ASCII the CRS of x/y (local-frame coordinates when absent, with `$.crs` the
    /// processing CRS).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crs: Option<u32>,
    /// An SBET's SMRMSG accuracy file, relative to the manifest's folder.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub accuracy_uri: Option<String>,
    /// The column layout of an ASCII trajectory.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ascii: Option<crate::trajectory_ascii::AsciiLayout>,
}

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StripRef {
    pub id: String,
    /// Id of an entry of `trajectories`.
    pub trajectory: String,
    /// Key of `scanners`.
    pub scanner: String,
    /// Relative to the manifest's folder (see [`resolve_uri`]).
    pub uri: String,
}

/// One problem: a JSON path like `$.strips[2].trajectory` and a message that says what is wrong
/// and what to do.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ManifestProblem {
    pub path: String,
    pub message: String,
}

impl fmt::Display for ManifestProblem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.path, self.message)
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ManifestError {
    #[error("cannot read manifest {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Displays every problem, one per line, as `file: $.path: message`.
    #[error("{}", render_problems(file.as_deref(), problems))]
    Invalid { file: Option<PathBuf>, problems: Vec<ManifestProblem> },
}

fn render_problems(file: Option<&Path>, problems: &[ManifestProblem]) -> String {
    let prefix = file.map(|f| format!("{}: ", f.display())).unwrap_or_default();
    if problems.is_empty() {
        return format!("{prefix}invalid manifest");
    }
    problems.iter().map(|p| format!("{prefix}{p}")).collect::<Vec<_>>().join("\n")
}

/// Reads and validates a manifest file; problems carry the file name.
pub fn load_manifest(path: &Path) -> Result<Manifest, ManifestError> {
    let text =
        std::fs::read_to_string(path).map_err(|source| ManifestError::Io { path: path.to_path_buf(), source })?;
    parse_manifest(&text).map_err(|e| match e {
        ManifestError::Invalid { problems, .. } => ManifestError::Invalid { file: Some(path.to_path_buf()), problems },
        other => other,
    })
}

/// Parses and validates manifest text, collecting all problems rather than stopping at the first.
pub fn parse_manifest(text: &str) -> Result<Manifest, ManifestError> {
    let invalid = |problems| ManifestError::Invalid { file: None, problems };
    let value: Value = match serde_json::from_str(text) {
        Ok(v) => v,
        Err(e) => return Err(invalid(vec![json_syntax_problem(&e)])),
    };
    let problems = Checker::check(&value);
    if !problems.is_empty() {
        return Err(invalid(problems));
    }
    // The walk above mirrors the serde model; should they ever disagree, serde's message still
    // reaches the user instead of a panic.
    serde_json::from_value(value).map_err(|e| invalid(vec![problem("$", e.to_string())]))
}

fn json_syntax_problem(e: &serde_json::Error) -> ManifestProblem {
    let full = e.to_string();
    let suffix = format!(" at line {} column {}", e.line(), e.column());
    let what = full.strip_suffix(&suffix).unwrap_or(&full);
    problem(
        "$",
        format!(
            "malformed JSON at line {}, column {}: {what}; fix the syntax there (common causes: a trailing comma, \
             a missing quote or bracket, NaN/Infinity or out-of-range numbers)",
            e.line(),
            e.column()
        ),
    )
}

fn problem(path: &str, message: impl Into<String>) -> ManifestProblem {
    ManifestProblem { path: path.to_string(), message: message.into() }
}

const EXAMPLE_URI: &str = "\"strips/p01-left.laz\"";

/// Resolves a manifest URI against the manifest's folder. Only relative paths inside that folder
/// are allowed: absolute paths, any scheme (`file://`, `s3://`, `http:`...), `..` components,
/// backslashes, empty strings, NUL and other control characters are rejected. `.` components are
/// dropped. (This is a lexical check: a symlink inside the folder can still point elsewhere.)
pub fn resolve_uri(manifest_dir: &Path, uri: &str) -> Result<PathBuf, String> {
    let advice = format!("use a path relative to the manifest's folder, such as {EXAMPLE_URI}");
    if uri.is_empty() {
        return Err(format!("uri is empty; {advice}"));
    }
    if uri.chars().any(char::is_control) {
        return Err(format!("uri {uri:?} contains a control character (NUL, newline...); {advice}"));
    }
    if uri.contains('\\') {
        return Err(format!("uri {uri:?} contains a backslash; separate folders with '/' and {advice}"));
    }
    if let Some((scheme, _)) = uri.split_once(':') {
        let looks_like_scheme = scheme.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
            && scheme.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.'));
        return Err(if looks_like_scheme {
            format!("uri {uri:?} has a scheme or drive ({scheme:?}); only files inside the manifest's folder may be read: {advice}")
        } else {
            format!("uri {uri:?} contains ':'; {advice}")
        });
    }
    if uri.starts_with('/') {
        return Err(format!("uri {uri:?} is an absolute path; {advice}"));
    }
    let mut out = manifest_dir.to_path_buf();
    let mut named = false;
    for part in uri.split('/') {
        match part {
            "" => return Err(format!("uri {uri:?} has an empty path component ('//' or a trailing '/'); {advice}")),
            "." => {}
            ".." => {
                return Err(format!(
                    "uri {uri:?} contains '..'; files outside the manifest's folder may not be read: {advice}"
                ))
            }
            p => {
                out.push(p);
                named = true;
            }
        }
    }
    if !named {
        return Err(format!("uri {uri:?} does not name a file; {advice}"));
    }
    Ok(out)
}

/// Ids become object-store keys and file names: keep them to a portable, harmless alphabet.
fn id_problem(id: &str, what: &str) -> Option<String> {
    let ok_chars = id.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
    if (1..=64).contains(&id.len()) && ok_chars && !id.starts_with('.') {
        return None;
    }
    Some(format!(
        "{what} {id:?} is not a safe file name: use 1–64 characters from A–Z, a–z, 0–9, '.', '_' and '-', \
         not starting with '.' (ids become file names and object keys)"
    ))
}

fn type_name(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// `$.a.b` for plain keys, `$.a["odd key"]` otherwise, so every path can be pasted into a JSONPath tool.
fn child(path: &str, key: &str) -> String {
    let plain = key.chars().next().is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && key.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    if plain {
        format!("{path}.{key}")
    } else {
        format!("{path}[{}]", Value::String(key.to_string()))
    }
}

fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut prev = row[0];
        row[0] = i + 1;
        for (j, &cb) in b.iter().enumerate() {
            let cur = row[j + 1];
            row[j + 1] = (prev + usize::from(ca != cb)).min(row[j] + 1).min(cur + 1);
            prev = cur;
        }
    }
    row[b.len()]
}

fn suggestion(key: &str, allowed: &[String]) -> String {
    allowed
        .iter()
        .map(|a| (edit_distance(key, a), a))
        .filter(|(d, a)| *d <= 2.max(a.len() / 4))
        .min()
        .map(|(_, a)| format!("did you mean {a:?}? "))
        .unwrap_or_default()
}

struct Checker {
    problems: Vec<ManifestProblem>,
}

/// The longest campaign name, in characters.
pub const MAX_NAME_CHARS: usize = 200;
/// The largest lever-arm component in metres (a scan head is on the vehicle).
pub const MAX_LEVER_ARM_M: f64 = 100.0;
/// The most iteration steps a schedule may list.
pub const MAX_SCHEDULE_STEPS: usize = 1000;

const TOP_FIELDS: [&str; 8] =
    ["name", "crs", "gps_week", "scanners", "trajectories", "strips", "parameters", "control"];
const SCANNER_FIELDS: [&str; 2] = ["lever_arm_m", "boresight_deg"];
const TRAJECTORY_FIELDS: [&str; 6] = ["id", "uri", "format", "crs", "accuracy_uri", "ascii"];
const STRIP_FIELDS: [&str; 4] = ["id", "trajectory", "scanner", "uri"];

impl Checker {
    fn check(root: &Value) -> Vec<ManifestProblem> {
        let mut c = Checker { problems: Vec::new() };
        let Some(top) = c.object("$", root, &TOP_FIELDS.map(String::from)) else {
            return c.problems;
        };

        if let Some(v) = c.required("$", top, "name", "a short campaign name, e.g. \"hannover-double-8\"") {
            match v.as_str() {
                Some(s) if s.trim().is_empty() => c.push("$.name", "is empty; give the campaign a name"),
                Some(s) if s.chars().count() > MAX_NAME_CHARS => c.push(
                    "$.name",
                    format!("is {} characters long; shorten it to at most {MAX_NAME_CHARS}", s.chars().count()),
                ),
                Some(s) if s.chars().any(char::is_control) => c.push(
                    "$.name",
                    "contains a control character (NUL, newline, tab...); use printable characters only",
                ),
                Some(_) => {}
                None => c.wrong_type("$.name", v, "a string"),
            }
        }
        let has_crs = c.crs(top);
        c.gps_week(top);
        let scanners = c.scanners(top);
        let trajectories = c.trajectories(top, has_crs);
        c.strips(top, scanners.as_ref(), trajectories.as_ref());
        if let Some(v) = top.get("parameters") {
            c.parameters(v);
        }
        let processing = top.get("crs").and_then(|crs| crs.get("processing")).and_then(Value::as_u64);
        c.control(top, processing.filter(|_| has_crs).and_then(|p| u32::try_from(p).ok()));
        c.problems
    }

    fn push(&mut self, path: &str, message: impl Into<String>) {
        self.problems.push(problem(path, message));
    }

    fn wrong_type(&mut self, path: &str, v: &Value, expected: &str) {
        self.push(path, format!("expected {expected}, found {}", type_name(v)));
    }

    /// The value as an object, reporting a wrong type and every unknown key.
    fn object<'v>(&mut self, path: &str, v: &'v Value, allowed: &[String]) -> Option<&'v Map<String, Value>> {
        let Some(map) = v.as_object() else {
            self.wrong_type(path, v, "an object");
            return None;
        };
        for key in map.keys() {
            if !allowed.contains(key) {
                self.push(
                    &child(path, key),
                    format!(
                        "unknown field {key:?}; {}remove it (allowed here: {})",
                        suggestion(key, allowed),
                        allowed.join(", ")
                    ),
                );
            }
        }
        Some(map)
    }

    fn required<'v>(&mut self, path: &str, map: &'v Map<String, Value>, key: &str, hint: &str) -> Option<&'v Value> {
        let v = map.get(key);
        if v.is_none() {
            self.push(&child(path, key), format!("missing required field {key:?}; add it: {hint}"));
        }
        v
    }

    fn required_str<'v>(&mut self, path: &str, map: &'v Map<String, Value>, key: &str, hint: &str) -> Option<&'v str> {
        let v = self.required(path, map, key, hint)?;
        let s = v.as_str();
        if s.is_none() {
            self.wrong_type(&child(path, key), v, "a string");
        }
        s
    }

    fn id(&mut self, path: &str, map: &Map<String, Value>, what: &str) -> Option<String> {
        let id = self.required_str(path, map, "id", "a unique name such as \"p01\"")?;
        if let Some(m) = id_problem(id, what) {
            self.push(&child(path, "id"), m);
        }
        Some(id.to_string())
    }

    fn uri(&mut self, path: &str, map: &Map<String, Value>) {
        if let Some(uri) =
            self.required_str(path, map, "uri", &format!("a path relative to the manifest, e.g. {EXAMPLE_URI}"))
        {
            // The folder is irrelevant for the lexical checks.
            if let Err(m) = resolve_uri(Path::new(""), uri) {
                self.push(&child(path, "uri"), m);
            }
        }
    }

    /// Three finite numbers, each of magnitude at most `bound`.
    fn vec3(&mut self, path: &str, v: &Value, unit: &str, bound: f64) {
        let numbers: Option<Vec<f64>> = v.as_array().and_then(|a| a.iter().map(Value::as_f64).collect());
        match numbers {
            Some(n) if n.len() == 3 => {
                if n.iter().any(|x| !x.is_finite()) {
                    self.push(path, format!("values must be finite numbers ({unit})"));
                }
                for (i, x) in n.iter().enumerate() {
                    if x.is_finite() && x.abs() > bound {
                        self.push(
                            &format!("{path}[{i}]"),
                            format!("{x} is out of range: use a value from {} to {bound} ({unit})", -bound),
                        );
                    }
                }
            }
            _ => self.push(path, format!("expected an array of 3 numbers [x, y, z] ({unit}), found {}", describe(v))),
        }
    }

    /// Returns the scanner names when `scanners` is usable, for the strips' reference checks.
    fn scanners(&mut self, top: &Map<String, Value>) -> Option<Vec<String>> {
        let v = self.required(
            "$",
            top,
            "scanners",
            "an object of scanner name → {\"lever_arm_m\": [x, y, z]}, e.g. {\"left\": {\"lever_arm_m\": [-0.6, 0.35, 0.45]}}",
        )?;
        let Some(map) = v.as_object() else {
            self.wrong_type("$.scanners", v, "an object of scanner name → scanner");
            return None;
        };
        let allowed = SCANNER_FIELDS.map(String::from);
        for (name, spec) in map {
            let path = child("$.scanners", name);
            if let Some(m) = id_problem(name, "scanner name") {
                self.push(&path, m);
            }
            let Some(fields) = self.object(&path, spec, &allowed) else { continue };
            if let Some(la) = self.required(
                &path,
                fields,
                "lever_arm_m",
                "the scan head's offset [x, y, z] in metres in the body frame",
            ) {
                self.vec3(
                    &child(&path, "lever_arm_m"),
                    la,
                    "metres, body frame x forward, y left, z up",
                    MAX_LEVER_ARM_M,
                );
            }
            if let Some(b) = fields.get("boresight_deg") {
                self.vec3(&child(&path, "boresight_deg"), b, "roll, pitch, yaw in degrees", 360.0);
            }
        }
        Some(map.keys().cloned().collect())
    }

    fn trajectories(&mut self, top: &Map<String, Value>, has_crs: bool) -> Option<Vec<String>> {
        let v = self.required("$", top, "trajectories", "an array of {\"id\": ..., \"uri\": ...}")?;
        let Some(items) = v.as_array() else {
            self.wrong_type("$.trajectories", v, "an array");
            return None;
        };
        let allowed = TRAJECTORY_FIELDS.map(String::from);
        let mut seen: HashMap<String, usize> = HashMap::new();
        for (i, item) in items.iter().enumerate() {
            let path = format!("$.trajectories[{i}]");
            let Some(map) = self.object(&path, item, &allowed) else { continue };
            if let Some(id) = self.id(&path, map, "trajectory id") {
                if let Some(first) = seen.get(&id) {
                    self.push(
                        &child(&path, "id"),
                        format!("duplicate trajectory id {id:?} (also $.trajectories[{first}]); give every trajectory a unique id"),
                    );
                } else {
                    seen.insert(id, i);
                }
            }
            self.uri(&path, map);
            self.trajectory_source(&path, map, has_crs);
        }
        Some(seen.into_keys().collect())
    }

    fn strips(&mut self, top: &Map<String, Value>, scanners: Option<&Vec<String>>, trajectories: Option<&Vec<String>>) {
        let Some(v) = self.required("$", top, "strips", "an array of {\"id\", \"trajectory\", \"scanner\", \"uri\"}")
        else {
            return;
        };
        let Some(items) = v.as_array() else {
            self.wrong_type("$.strips", v, "an array");
            return;
        };
        if items.is_empty() {
            self.push(
                "$.strips",
                "is empty; list at least one strip (a LAS/LAZ file of one scanner on one trajectory)",
            );
        }
        let allowed = STRIP_FIELDS.map(String::from);
        let mut seen: HashMap<String, usize> = HashMap::new();
        for (i, item) in items.iter().enumerate() {
            let path = format!("$.strips[{i}]");
            let Some(map) = self.object(&path, item, &allowed) else { continue };
            if let Some(id) = self.id(&path, map, "strip id") {
                if let Some(first) = seen.get(&id) {
                    self.push(
                        &child(&path, "id"),
                        format!("duplicate strip id {id:?} (also $.strips[{first}]); give every strip a unique id"),
                    );
                } else {
                    seen.insert(id, i);
                }
            }
            if let Some(t) = self.required_str(&path, map, "trajectory", "the id of an entry of $.trajectories") {
                // When $.trajectories itself is broken that is reported once, not again per strip.
                if trajectories.is_some_and(|ids| !ids.iter().any(|x| x == t)) {
                    self.push(
                        &child(&path, "trajectory"),
                        format!(
                            "trajectory {t:?} is not listed; add a trajectory with id {t:?} to $.trajectories or fix \
                             the strip's trajectory field"
                        ),
                    );
                }
            }
            if let Some(s) = self.required_str(&path, map, "scanner", "a key of $.scanners") {
                if let Some(names) = scanners.filter(|names| !names.iter().any(|x| x == s)) {
                    let known = if names.is_empty() { "none".to_string() } else { names.join(", ") };
                    self.push(
                        &child(&path, "scanner"),
                        format!(
                            "scanner {s:?} is not listed (known: {known}); add {s:?} to $.scanners or fix the strip's \
                             scanner field"
                        ),
                    );
                }
            }
            self.uri(&path, map);
        }
    }

    fn parameters(&mut self, v: &Value) {
        let before = self.problems.len();
        // The defaults' JSON shape is the schema: new fields in core are picked up automatically.
        let mut template = match serde_json::to_value(Parameters::default()) {
            Ok(t) => t,
            Err(e) => return self.push("$.parameters", format!("internal error describing parameters: {e}")),
        };
        // Optional fields absent from the defaults' JSON; their values are checked by parsing.
        if let Some(t) = template.as_object_mut() {
            t.entry("ring").or_insert(Value::Null);
            t.entry("process_model").or_insert(Value::Null);
            // Checked on its own below: its fields are all optional.
            t.entry("calibration").or_insert(Value::Null);
        }
        self.like("$.parameters", v, &template, false);
        if let Some(calibration) = v.get("calibration") {
            let options = precimap_core::CalibrationOptions {
                estimate: vec![precimap_core::CalibrationUnknown::Boresight],
                ..Default::default()
            };
            if let Ok(t) = serde_json::to_value(options) {
                self.like("$.parameters.calibration", calibration, &t, false);
            }
        }
        if self.problems.len() > before {
            return;
        }
        self.parameter_ranges("$.parameters", v);
        match serde_json::from_value::<Parameters>(v.clone()) {
            Ok(p) => {
                for pp in p.problems() {
                    self.push(
                        &format!("$.parameters.{}", pp.field),
                        format!("{}; change the value (or omit the field to use the paper's default)", pp.problem),
                    );
                }
            }
            Err(e) => self.push("$.parameters", e.to_string()),
        }
    }

    /// Bounds no sensible campaign comes near, so that a typo (a value in millimetres, an
    /// exponent too many) is refused at submission rather than found hours into a run, or never:
    /// lengths within ±10 km, angles within ±360°, anything else within ±10⁶; the spacings that
    /// set how much work there is (anchors, tiles, cells, grids) at least 1 mm or 1 cm; at most
    /// `MAX_SCHEDULE_STEPS` iterations. The core's own checks (positive, in [0, 1)...) follow.
    fn parameter_ranges(&mut self, path: &str, v: &Value) {
        match v {
            Value::Object(map) => {
                for (key, x) in map {
                    let here = child(path, key);
                    if let Some(x) = x.as_f64() {
                        self.parameter_range(&here, key, x);
                    } else {
                        self.parameter_ranges(&here, x);
                    }
                }
            }
            Value::Array(items) => {
                if items.len() > MAX_SCHEDULE_STEPS {
                    self.push(
                        path,
                        format!("has {} steps; a campaign runs at most {MAX_SCHEDULE_STEPS} iterations", items.len()),
                    );
                }
                for (i, x) in items.iter().enumerate() {
                    self.parameter_ranges(&format!("{path}[{i}]"), x);
                }
            }
            _ => {}
        }
    }

    fn parameter_range(&mut self, path: &str, field: &str, x: f64) {
        let (bound, unit) = if field.ends_with("_m") {
            (10_000.0, " m")
        } else if field.ends_with("_deg") {
            (360.0, "°")
        } else {
            (1e6, "")
        };
        let least = match field {
            "anchor_spacing_m" | "tile_size_m" => Some(0.01),
            "cell_size_m" | "grid_m" | "cell_m" => Some(0.001),
            _ => None,
        };
        if x.abs() > bound {
            self.push(path, format!("{x} is out of range: use a value within ±{bound}{unit}"));
        } else if let Some(least) = least.filter(|least| x > 0.0 && x < *least) {
            self.push(
                path,
                format!(
                    "{x}{unit} is too fine: at least {least}{unit} (finer spacings multiply the work without bound)"
                ),
            );
        }
    }

    /// Checks `v` against the shape of `template`. Objects nested in arrays (schedule steps)
    /// need the fields core declares required; the top-level parameters object needs none
    /// (every field has a default).
    fn like(&mut self, path: &str, v: &Value, template: &Value, all_required: bool) {
        match template {
            Value::Object(t) => {
                let allowed: Vec<String> = t.keys().cloned().collect();
                let Some(map) = self.object(path, v, &allowed) else { return };
                for (key, sub) in t {
                    match map.get(key) {
                        Some(x) => self.like(&child(path, key), x, sub, true),
                        None if all_required => {
                            self.push(&child(path, key), format!("missing required field {key:?}; add it"))
                        }
                        None => {}
                    }
                }
            }
            Value::Array(t) => {
                let Some(items) = v.as_array() else { return self.wrong_type(path, v, "an array") };
                if let Some(element) = t.first() {
                    for (i, x) in items.iter().enumerate() {
                        let item = format!("{path}[{i}]");
                        self.like(&item, x, element, false);
                        if let Some(map) = x.as_object() {
                            for key in precimap_core::IterationStep::REQUIRED_FIELDS {
                                if !map.contains_key(key) {
                                    self.push(&child(&item, key), format!("missing required field {key:?}; add it"));
                                }
                            }
                        }
                    }
                }
            }
            // Counts (`anderson_depth`): the defaults' JSON holds them as unsigned integers.
            Value::Number(t) if t.is_u64() && !v.is_u64() => {
                self.push(path, format!("expected a whole number (0 or more), found {}", describe(v)))
            }
            Value::Number(_) if !v.is_number() => self.wrong_type(path, v, "a number"),
            Value::String(_) if !v.is_string() => self.wrong_type(path, v, "a string"),
            Value::Bool(_) if !v.is_boolean() => self.wrong_type(path, v, "a boolean"),
            _ => {}
        }
    }
}

/// Short description of a value for messages: the value itself when small.
fn describe(v: &Value) -> String {
    let s = v.to_string();
    if s.len() <= 40 {
        s
    } else {
        type_name(v).to_string()
    }
}

#[cfg(test)]
mod tests;
