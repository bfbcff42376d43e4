//! The manifest's field-input parts: the processing CRS and its local frame, the GPS week, and
//! per trajectory its file format, CRS, accuracy file and ASCII layout.

use super::{child, describe, Checker};
use crate::crs::{Crs, LocalFrame};
use crate::trajectory_ascii::AsciiLayout;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

/// How a trajectory file is read.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrajectoryFormat {
    /// precimap's CSV `time,x,y,z,roll,pitch,yaw`.
    #[default]
    Csv,
    /// Applanix SBET (binary, geographic, radians, GPS week seconds).
    Sbet,
    /// A text export described by `ascii`.
    Ascii,
}

impl TrajectoryFormat {
    pub fn is_csv(&self) -> bool {
        *self == Self::Csv
    }
}

/// `$.crs`: the processing CRS and the origin of the local frame estimation runs in.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CrsSpec {
    /// EPSG code of the projected CRS results are written in (e.g. 32632).
    pub processing: u32,
    /// Grid coordinates (easting, northing, ellipsoidal height) of the local frame's origin: a
    /// point near the middle of the campaign.
    pub origin_grid_m: [f64; 3],
    /// EPSG code of the strips' coordinates where a strip does not declare its CRS, and the CRS a
    /// declared one must match; the processing CRS when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strips: Option<u32>,
}

impl CrsSpec {
    /// The processing frame.
    pub fn frame(&self) -> Result<LocalFrame, crate::crs::CrsError> {
        LocalFrame::new(Crs::from_epsg(self.processing)?, self.origin_grid_m)
    }

    /// The CRS of the strip files.
    pub fn strip_crs(&self) -> Result<Crs, crate::crs::CrsError> {
        Crs::from_epsg(self.strips.unwrap_or(self.processing))
    }

    /// The processing frame and the strips' CRS.
    pub fn georeference(&self) -> Result<crate::crs::Georeference, crate::crs::CrsError> {
        Ok(crate::crs::Georeference { frame: self.frame()?, strip_crs: self.strip_crs()? })
    }
}

impl super::TrajectoryRef {
    /// A trajectory CSV in the campaign's frame.
    pub fn csv(id: impl Into<String>, uri: impl Into<String>) -> Self {
        Self {
            id: id.into(),
            uri: uri.into(),
            format: TrajectoryFormat::Csv,
            crs: None,
            accuracy_uri: None,
            ascii: None,
        }
    }
}

pub(super) const CRS_FIELDS: [&str; 3] = ["processing", "origin_grid_m", "strips"];
/// The largest plausible GPS week (continuous count since 1980).
pub const MAX_GPS_WEEK: u64 = 10_000;

impl Checker {
    fn epsg(&mut self, path: &str, v: &Value) -> Option<Crs> {
        let Some(code) = v.as_u64() else {
            self.push(path, format!("expected an EPSG code (a whole number such as 32632), found {}", describe(v)));
            return None;
        };
        match Crs::from_epsg(u32::try_from(code).unwrap_or(u32::MAX)) {
            Ok(c) => Some(c),
            Err(e) => {
                self.push(path, e.to_string());
                None
            }
        }
    }

    /// `$.crs`; returns whether it is usable (trajectories that need it are checked against that).
    pub(super) fn crs(&mut self, top: &Map<String, Value>) -> bool {
        let Some(v) = top.get("crs") else { return false };
        let Some(map) = self.object("$.crs", v, &CRS_FIELDS.map(String::from)) else { return false };
        let before = self.problems.len();
        let processing = self
            .required("$.crs", map, "processing", "the EPSG code of the projected CRS to work in, e.g. 32632")
            .and_then(|v| self.epsg("$.crs.processing", v));
        if let Some(c) = processing.as_ref().filter(|c| c.is_geographic()) {
            self.push(
                "$.crs.processing",
                format!("{c} is geographic; name a projected CRS in metres, such as the campaign's UTM zone"),
            );
        }
        let origin = self
            .required(
                "$.crs",
                map,
                "origin_grid_m",
                "[easting, northing, height] of a point near the middle of the campaign",
            )
            .cloned();
        if let Some(o) = &origin {
            self.vec3("$.crs.origin_grid_m", o, "metres in the processing CRS", 1e8);
        }
        if let Some(s) = map.get("strips") {
            if let Some(c) = self.epsg("$.crs.strips", s) {
                if c.is_geographic() {
                    self.push(
                        "$.crs.strips",
                        format!("{c} is geographic; LAS strips need projected coordinates in metres"),
                    );
                }
            }
        }
        if self.problems.len() > before {
            return false;
        }
        let spec: Result<CrsSpec, _> = serde_json::from_value(v.clone());
        match spec.map(|s| s.frame()) {
            Ok(Ok(_)) => true,
            Ok(Err(e)) => {
                self.push(
                    "$.crs.origin_grid_m",
                    format!("{e}; give grid coordinates inside the processing CRS's area"),
                );
                false
            }
            Err(e) => {
                self.push("$.crs", e.to_string());
                false
            }
        }
    }

    pub(super) fn gps_week(&mut self, top: &Map<String, Value>) {
        if let Some(v) = top.get("gps_week") {
            if v.as_u64().is_none_or(|w| w > MAX_GPS_WEEK) {
                self.push(
                    "$.gps_week",
                    format!(
                        "expected the GPS week of the campaign (a whole number, weeks since 1980-01-06 without \
                         rollover, e.g. 2311), found {}",
                        describe(v)
                    ),
                );
            }
        }
    }

    /// A trajectory's `format`, `crs`, `accuracy_uri` and `ascii`.
    pub(super) fn trajectory_source(&mut self, path: &str, map: &Map<String, Value>, has_crs: bool) {
        let format = match map.get("format") {
            None => Some(TrajectoryFormat::Csv),
            Some(v) => match serde_json::from_value::<TrajectoryFormat>(v.clone()) {
                Ok(f) => Some(f),
                Err(_) => {
                    self.push(
                        &child(path, "format"),
                        format!("expected \"csv\", \"sbet\" or \"ascii\", found {}", describe(v)),
                    );
                    None
                }
            },
        };
        let own_crs = map.get("crs").and_then(|v| self.epsg(&child(path, "crs"), v));
        let needs_frame = own_crs.is_some() || format == Some(TrajectoryFormat::Sbet);
        if needs_frame && !has_crs {
            self.push(
                path,
                "this trajectory is geographic or in a CRS, which needs a usable $.crs: add \"crs\": {\"processing\": \
                 EPSG code, \"origin_grid_m\": [easting, northing, height]} at the top of the manifest",
            );
        }
        if let Some(uri) = map.get("accuracy_uri") {
            let at = child(path, "accuracy_uri");
            if format != Some(TrajectoryFormat::Sbet) {
                self.push(
                    &at,
                    "an accuracy (SMRMSG) file belongs to an SBET trajectory; remove it or set \"format\": \"sbet\"",
                );
            }
            match uri.as_str() {
                Some(u) => {
                    if let Err(m) = super::resolve_uri(std::path::Path::new(""), u) {
                        self.push(&at, m);
                    }
                }
                None => self.wrong_type(&at, uri, "a string"),
            }
        }
        let at = child(path, "ascii");
        match (format, map.get("ascii")) {
            (Some(TrajectoryFormat::Ascii), None) => self.push(
                &at,
                "missing: an ASCII trajectory needs its layout, e.g. {\"delimiter\": \",\", \"header_lines\": 1, \
                 \"columns\": {\"time\": 0, \"x\": 1, \"y\": 2, \"z\": 3, \"roll\": 4, \"pitch\": 5, \"heading\": 6}}",
            ),
            (Some(TrajectoryFormat::Ascii), Some(v)) => match serde_json::from_value::<AsciiLayout>(v.clone()) {
                Ok(layout) => {
                    for (field, m) in layout.problems() {
                        self.push(&child(&at, field), m);
                    }
                }
                Err(e) => self.push(&at, format!("{e}; see docs/user/parameters.md for the layout's fields")),
            },
            (Some(_), Some(_)) => {
                self.push(&at, "a layout belongs to \"format\": \"ascii\"; remove it or change the format")
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{parse_manifest, ManifestError, ManifestProblem};
    use super::*;

    const FIELD: &str = r#"{
      "name": "field",
      "crs": {"processing": 32632, "origin_grid_m": [549800, 5803400, 55]},
      "gps_week": 2311,
      "scanners": {"left": {"lever_arm_m": [-0.6, 0.35, 0.45]}},
      "trajectories": [
        {"id": "p01", "uri": "trajectories/p01.sbet", "format": "sbet", "accuracy_uri": "trajectories/p01.smrmsg"},
        {"id": "p02", "uri": "trajectories/p02.txt", "format": "ascii", "crs": 4326,
         "ascii": {"delimiter": "whitespace", "header_lines": 1, "angle_unit": "deg", "attitude": "navigation",
                   "time": "week_seconds",
                   "columns": {"time": 0, "y": 1, "x": 2, "z": 3, "roll": 4, "pitch": 5, "heading": 6}}},
        {"id": "p03", "uri": "trajectories/p03.csv"}
      ],
      "strips": [{"id": "s1", "trajectory": "p01", "scanner": "left", "uri": "strips/s1.laz"}]
    }"#;

    fn problems(text: &str) -> Vec<ManifestProblem> {
        match parse_manifest(text) {
            Err(ManifestError::Invalid { problems, .. }) => problems,
            other => panic!("expected problems, got {other:?}"),
        }
    }

    fn with(edit: impl FnOnce(&mut Value)) -> String {
        let mut v: Value = serde_json::from_str(FIELD).unwrap();
        edit(&mut v);
        v.to_string()
    }

    fn has(p: &[ManifestProblem], path: &str, needle: &str) -> bool {
        p.iter().any(|x| x.path == path && x.message.contains(needle))
    }

    #[test]
    fn field_manifest_parses_and_round_trips() {
        let m = parse_manifest(FIELD).unwrap();
        let crs = m.crs.as_ref().unwrap();
        assert_eq!((crs.processing, crs.strips, m.gps_week), (32632, None, Some(2311)));
        assert_eq!(crs.strip_crs().unwrap().epsg(), 32632);
        assert!((crs.frame().unwrap().convergence_deg() - 0.57).abs() < 0.02);
        assert_eq!(m.trajectories[0].format, TrajectoryFormat::Sbet);
        assert_eq!(m.trajectories[1].ascii.as_ref().unwrap().columns.y, 1);
        assert_eq!(m.trajectories[2].format, TrajectoryFormat::Csv);
        let again = parse_manifest(&serde_json::to_string(&m).unwrap()).unwrap();
        assert_eq!(again, m);
        // A local-frame manifest serializes without any of the field inputs' keys.
        let local = with(|v| {
            let o = v.as_object_mut().unwrap();
            o.remove("crs");
            o.remove("gps_week");
            v["trajectories"] = serde_json::json!([{"id": "p01", "uri": "p01.csv"}]);
        });
        let text = serde_json::to_string(&parse_manifest(&local).unwrap()).unwrap();
        for key in ["crs", "gps_week", "format", "accuracy_uri", "ascii"] {
            assert!(!text.contains(&format!("\"{key}\"")), "{key} in {text}");
        }
    }

    #[test]
    fn bad_crs_week_and_sources_are_named() {
        let p = problems(&with(|v| {
            v["crs"]["processing"] = Value::from(4326);
            v["crs"]["strips"] = Value::from(12);
            v["gps_week"] = Value::from(-3);
            v["trajectories"][0]["format"] = Value::from("sbet2");
            v["trajectories"][1].as_object_mut().unwrap().remove("ascii");
            v["trajectories"][2]["accuracy_uri"] = Value::from("../x");
        }));
        assert!(has(&p, "$.crs.processing", "is geographic"), "{p:#?}");
        assert!(has(&p, "$.crs.strips", "not in the EPSG registry"), "{p:#?}");
        assert!(has(&p, "$.gps_week", "found -3"), "{p:#?}");
        assert!(has(&p, "$.trajectories[0].format", "\"csv\", \"sbet\" or \"ascii\""), "{p:#?}");
        assert!(has(&p, "$.trajectories[1].ascii", "missing"), "{p:#?}");
        assert!(has(&p, "$.trajectories[2].accuracy_uri", "belongs to an SBET"), "{p:#?}");
        assert!(has(&p, "$.trajectories[2].accuracy_uri", "'..'"), "{p:#?}");
        // Without a usable $.crs, geographic trajectories are refused where they are listed.
        let p = problems(&with(|v| {
            v.as_object_mut().unwrap().remove("crs");
        }));
        assert!(has(&p, "$.trajectories[0]", "needs a usable $.crs"), "{p:#?}");
        assert!(has(&p, "$.trajectories[1]", "needs a usable $.crs"), "{p:#?}");
        assert_eq!(p.len(), 2, "{p:#?}");
        let p = problems(&with(|v| {
            v["crs"]["origin_grid_m"] = serde_json::json!([5e7, 5803400, 55]);
            v["trajectories"][1]["ascii"]["delimiter"] = Value::from("ab");
            v["trajectories"][1]["ascii"]["angle_unit"] = Value::from("grad");
        }));
        assert!(has(&p, "$.crs.origin_grid_m", "cannot transform"), "{p:#?}");
        assert!(has(&p, "$.trajectories[1].ascii", "grad"), "{p:#?}");
        let p = problems(&with(|v| v["trajectories"][1]["ascii"]["delimiter"] = Value::from("ab")));
        assert!(has(&p, "$.trajectories[1].ascii.delimiter", "one character"), "{p:#?}");
        let p = problems(&with(|v| v["crs"]["origin"] = Value::from(1)));
        assert!(has(&p, "$.crs.origin", "unknown field"), "{p:#?}");
    }
}
