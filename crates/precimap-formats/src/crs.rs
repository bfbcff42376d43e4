//! Coordinate reference systems and the processing frame (docs/design/field-inputs.md).
//!
//! A CRS is named by its EPSG code; its definition (a PROJ string and WKT) comes from the EPSG
//! registry compiled into `crs-definitions`, and projections run through `proj4rs` (pure Rust,
//! the Poder/Engsager transverse Mercator for UTM).
//!
//! Estimation runs in a **local Cartesian frame** derived from the projected processing CRS, not
//! in the projected grid itself: the grid is conformal but not metric (UTM scales horizontal
//! distances by k ≈ 0.9996…1.0010, heights not at all) and it ignores Earth curvature, while
//! lever arms, ranges and pose corrections are true metres and angles. The local frame is the
//! east-north-up tangent frame at the origin `O` (given in grid coordinates), turned about the
//! vertical so that its x/y axes are parallel to grid east/north at `O`, and offset so that at `O`
//! its coordinates equal the grid coordinates: near `O` the numbers look like grid coordinates
//! (tiles stay in absolute coordinates), distances and angles are exact everywhere.
//!
//! Heights are ellipsoidal (no geoid model); inputs in a geographic CRS on another datum than the
//! processing CRS are converted by `proj4rs`'s datum transformation (`towgs84`), which for WGS 84 ↔
//! ETRS89 is the identity.

use precimap_core::{Mat3, Vec3};
use proj4rs::Proj;
use std::fmt;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CrsError {
    #[error(
        "EPSG:{0} is not in the EPSG registry precimap knows; name a projected CRS such as 32632 (WGS 84 / UTM zone \
         32N) or 25832 (ETRS89 / UTM zone 32N), or a geographic one such as 4979 (WGS 84, 3D)"
    )]
    Unknown(u32),
    #[error("EPSG:{code} ({name}): {message}")]
    Unsupported { code: u32, name: String, message: String },
    #[error("cannot transform ({}, {}, {}) from {from} to {to}: {message}", point[0], point[1], point[2])]
    Transform { point: [f64; 3], from: String, to: String, message: String },
}

/// A coordinate reference system from the EPSG registry.
#[derive(Clone)]
pub struct Crs {
    code: u16,
    wkt: &'static str,
    proj: Proj,
    /// Geographic coordinates (radians) on the same datum, the bridge to Cartesian coordinates.
    geographic: Proj,
    /// Semi-major axis and first eccentricity squared of the datum's ellipsoid.
    a: f64,
    e2: f64,
}

impl fmt::Debug for Crs {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Crs({self})")
    }
}

impl fmt::Display for Crs {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "EPSG:{} ({})", self.code, self.name())
    }
}

impl PartialEq for Crs {
    fn eq(&self, other: &Self) -> bool {
        self.code == other.code
    }
}

/// The PROJ tokens that define a datum (kept when deriving the geographic CRS of a projected one).
const DATUM_TOKENS: [&str; 9] = ["+datum=", "+ellps=", "+towgs84=", "+a=", "+b=", "+rf=", "+f=", "+pm=", "+nadgrids="];

impl Crs {
    pub fn from_epsg(code: u32) -> Result<Self, CrsError> {
        let short = u16::try_from(code).map_err(|_| CrsError::Unknown(code))?;
        let def = crs_definitions::from_code(short).ok_or(CrsError::Unknown(code))?;
        let unsupported =
            |message: String| CrsError::Unsupported { code, name: wkt_name(def.wkt).to_string(), message };
        let proj = Proj::from_proj_string(def.proj4)
            .map_err(|e| unsupported(format!("its definition `{}` cannot be used ({e})", def.proj4)))?;
        if proj.is_geocent() {
            return Err(unsupported("geocentric CRSs are not supported; use a geographic or projected CRS".into()));
        }
        if !proj.is_latlong() && (proj.to_meter() != 1.0 || proj.vto_meter() != 1.0) {
            return Err(unsupported(format!(
                "its unit is not the metre (`{}`); use a CRS in metres such as the UTM zone of the campaign",
                def.proj4
            )));
        }
        let datum: Vec<&str> =
            def.proj4.split_whitespace().filter(|t| DATUM_TOKENS.iter().any(|d| t.starts_with(d))).collect();
        let geo_def = format!("+proj=longlat {}", datum.join(" "));
        let geographic = Proj::from_proj_string(&geo_def)
            .map_err(|e| unsupported(format!("its datum `{geo_def}` cannot be used ({e})")))?;
        let (a, b) = proj.ellipse_parameters();
        Ok(Self { code: short, wkt: def.wkt, proj, geographic, a, e2: 1.0 - (b * b) / (a * a) })
    }

    pub fn epsg(&self) -> u32 {
        u32::from(self.code)
    }

    /// The name in the registry's WKT, e.g. `WGS 84 / UTM zone 32N`.
    pub fn name(&self) -> &'static str {
        wkt_name(self.wkt)
    }

    /// The registry's WKT (what a LAS WKT VLR carries).
    pub fn wkt(&self) -> &'static str {
        self.wkt
    }

    pub fn is_geographic(&self) -> bool {
        self.proj.is_latlong()
    }

    fn transform(&self, from: &Proj, to: &Proj, p: [f64; 3], names: (&str, &str)) -> Result<[f64; 3], CrsError> {
        let mut q = (p[0], p[1], p[2]);
        let failed = |message: String| CrsError::Transform {
            point: p,
            from: names.0.to_string(),
            to: names.1.to_string(),
            message,
        };
        proj4rs::transform::transform(from, to, &mut q).map_err(|e| failed(e.to_string()))?;
        if !(q.0.is_finite() && q.1.is_finite() && q.2.is_finite()) {
            return Err(failed("the result is not finite (the point lies outside the projection's domain)".into()));
        }
        Ok([q.0, q.1, q.2])
    }

    /// Grid (easting, northing, height) → (longitude, latitude in radians, height) on this datum.
    pub fn to_geographic(&self, p: [f64; 3]) -> Result<[f64; 3], CrsError> {
        if self.is_geographic() {
            return Ok(p);
        }
        self.transform(&self.proj, &self.geographic, p, (&self.to_string(), "its geographic coordinates"))
    }

    /// (longitude, latitude in radians, height) on this datum → grid (easting, northing, height).
    pub fn from_geographic(&self, p: [f64; 3]) -> Result<[f64; 3], CrsError> {
        if self.is_geographic() {
            return Ok(p);
        }
        self.transform(&self.geographic, &self.proj, p, ("its geographic coordinates", &self.to_string()))
    }

    /// Geographic coordinates (radians) of `other`'s datum → this CRS's datum.
    pub fn geographic_from(&self, other: &Crs, p: [f64; 3]) -> Result<[f64; 3], CrsError> {
        if other.geographic_definition_equals(self) {
            return Ok(p);
        }
        self.transform(&other.geographic, &self.geographic, p, (&other.to_string(), &self.to_string()))
    }

    /// Meridian convergence at (longitude, latitude in radians, height) of this datum: the angle
    /// from true north to grid north, clockwise, radians; 0 for a geographic CRS.
    pub fn convergence(&self, g: [f64; 3]) -> Result<f64, CrsError> {
        if self.is_geographic() {
            return Ok(0.0);
        }
        Ok(-grid_azimuth_of_north(self, g[0], g[1], g[2])?)
    }

    fn geographic_definition_equals(&self, other: &Crs) -> bool {
        let datum = |c: &Crs| {
            let def = crs_definitions::from_code(c.code).map(|d| d.proj4).unwrap_or("");
            def.split_whitespace().filter(|t| DATUM_TOKENS.iter().any(|d| t.starts_with(d))).collect::<Vec<_>>()
        };
        datum(self) == datum(other)
    }

    /// Earth-centred Cartesian coordinates of (longitude, latitude in radians, ellipsoidal height).
    pub fn ecef(&self, [lon, lat, h]: [f64; 3]) -> Vec3 {
        let (sp, cp) = lat.sin_cos();
        let (sl, cl) = lon.sin_cos();
        let n = self.a / (1.0 - self.e2 * sp * sp).sqrt();
        Vec3::new((n + h) * cp * cl, (n + h) * cp * sl, (n * (1.0 - self.e2) + h) * sp)
    }

    /// Inverse of [`Crs::ecef`]: (longitude, latitude in radians, height).
    pub fn geodetic(&self, x: &Vec3) -> [f64; 3] {
        let lon = x.y.atan2(x.x);
        let p = x.x.hypot(x.y);
        let mut lat = x.z.atan2(p * (1.0 - self.e2));
        // Fixed-point iteration: converges by a factor ~e² per step near the ellipsoid.
        for _ in 0..12 {
            let s = lat.sin();
            let n = self.a / (1.0 - self.e2 * s * s).sqrt();
            let h = p * lat.cos() + x.z * s - self.a * self.a / n;
            let next = x.z.atan2(p * (1.0 - self.e2 * n / (n + h)));
            let done = (next - lat).abs() < 1e-15;
            lat = next;
            if done {
                break;
            }
        }
        let (s, c) = lat.sin_cos();
        let n = self.a / (1.0 - self.e2 * s * s).sqrt();
        [lon, lat, p * c + x.z * s - self.a * self.a / n]
    }
}

fn wkt_name(wkt: &str) -> &str {
    wkt.split_once("[\"").and_then(|(_, rest)| rest.split_once('"')).map_or("unnamed", |(name, _)| name)
}

/// East, north and up at (longitude, latitude) as the columns of a matrix in Earth-centred axes.
pub fn ecef_from_enu(lon: f64, lat: f64) -> Mat3 {
    let (sp, cp) = lat.sin_cos();
    let (sl, cl) = lon.sin_cos();
    Mat3::new(-sl, -sp * cl, cp * cl, cl, -sp * sl, cp * sl, 0.0, cp, sp)
}

/// North-east-down → east-north-up (its own inverse).
pub const ENU_FROM_NED: Mat3 = Mat3::new(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0);

/// precimap's body frame (x forward, y left, z up) → the navigation body frame of SBET and most
/// INS exports (x forward, y right, z down); its own inverse.
pub const NAV_BODY_FROM_BODY: Mat3 = Mat3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0);

/// The processing frame: a local Cartesian frame derived from a projected CRS (module docs).
#[derive(Clone, Debug)]
pub struct LocalFrame {
    crs: Crs,
    origin_grid: Vec3,
    origin_ecef: Vec3,
    /// Earth-centred axes → local axes.
    local_from_ecef: Mat3,
    /// Meridian convergence at the origin (radians): the angle from true north to grid north,
    /// clockwise (positive east of a UTM zone's central meridian in the northern hemisphere).
    convergence: f64,
}

impl LocalFrame {
    /// The frame with its origin at grid coordinates `origin_grid_m` (easting, northing,
    /// ellipsoidal height) of the projected CRS `crs`.
    pub fn new(crs: Crs, origin_grid_m: [f64; 3]) -> Result<Self, CrsError> {
        if crs.is_geographic() {
            return Err(CrsError::Unsupported {
                code: crs.epsg(),
                name: crs.name().to_string(),
                message: "the processing CRS must be projected (in metres), such as the campaign's UTM zone".into(),
            });
        }
        let [lon, lat, h] = crs.to_geographic(origin_grid_m)?;
        // Far outside a projection's area its inverse returns numbers that do not map back.
        let back = crs.from_geographic([lon, lat, h])?;
        if (back[0] - origin_grid_m[0]).hypot(back[1] - origin_grid_m[1]) > 1e-3 {
            return Err(CrsError::Transform {
                point: origin_grid_m,
                from: crs.to_string(),
                to: "geographic coordinates".into(),
                message: "the point lies outside the projection's area".into(),
            });
        }
        let convergence = crs.convergence([lon, lat, h])?;
        let (s, c) = convergence.sin_cos();
        // Rows: grid east and grid north at the origin in east-north-up (grid north lies at true
        // azimuth γ), then up.
        let local_from_enu = Mat3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
        let local_from_ecef = local_from_enu * ecef_from_enu(lon, lat).transpose();
        let origin_ecef = crs.ecef([lon, lat, h]);
        Ok(Self { crs, origin_grid: Vec3::from(origin_grid_m), origin_ecef, local_from_ecef, convergence })
    }

    pub fn crs(&self) -> &Crs {
        &self.crs
    }

    pub fn origin_grid_m(&self) -> [f64; 3] {
        self.origin_grid.into()
    }

    /// Meridian convergence at the origin, degrees (from true north to grid north, clockwise).
    pub fn convergence_deg(&self) -> f64 {
        self.convergence.to_degrees()
    }

    pub fn local_from_ecef(&self, x: &Vec3) -> Vec3 {
        self.local_from_ecef * (x - self.origin_ecef) + self.origin_grid
    }

    pub fn ecef_from_local(&self, p: &Vec3) -> Vec3 {
        self.local_from_ecef.transpose() * (p - self.origin_grid) + self.origin_ecef
    }

    /// Geographic coordinates of this frame's datum (longitude, latitude in radians, height) →
    /// local.
    pub fn local_from_geographic(&self, g: [f64; 3]) -> Vec3 {
        self.local_from_ecef(&self.crs.ecef(g))
    }

    pub fn geographic_from_local(&self, p: &Vec3) -> [f64; 3] {
        self.crs.geodetic(&self.ecef_from_local(p))
    }

    /// Grid coordinates of the processing CRS → local.
    pub fn local_from_grid(&self, p: [f64; 3]) -> Result<Vec3, CrsError> {
        Ok(self.local_from_geographic(self.crs.to_geographic(p)?))
    }

    /// Local → grid coordinates of the processing CRS.
    pub fn grid_from_local(&self, p: &Vec3) -> Result<[f64; 3], CrsError> {
        self.crs.from_geographic(self.geographic_from_local(p))
    }

    /// Rotation from the local-level north-east-down frame at (longitude, latitude) to the local
    /// frame's axes.
    pub fn local_from_ned(&self, lon: f64, lat: f64) -> Mat3 {
        self.local_from_ecef * ecef_from_enu(lon, lat) * ENU_FROM_NED
    }

    /// precimap's attitude (`R_local_body`, body x forward, y left, z up) of a navigation attitude:
    /// roll, pitch and true heading (radians) about the body's forward, right and down axes, as
    /// `R_ned_navbody = Rz(heading)·Ry(pitch)·Rx(roll)` in the local-level frame at (lon, lat).
    pub fn body_rotation_from_navigation(&self, lon: f64, lat: f64, roll: f64, pitch: f64, heading: f64) -> Mat3 {
        let ned_from_nav = precimap_core::geom::rot_from_rpy(roll, pitch, heading);
        self.local_from_ned(lon, lat) * ned_from_nav * NAV_BODY_FROM_BODY
    }

    /// `R_local_body` of an attitude `R_enu_body` given in the east-north-up frame at (lon, lat).
    pub fn body_rotation_from_enu(&self, lon: f64, lat: f64, enu_from_body: &Mat3) -> Mat3 {
        self.local_from_ecef * ecef_from_enu(lon, lat) * enu_from_body
    }

    /// Inverse of [`LocalFrame::body_rotation_from_enu`].
    pub fn enu_from_body_rotation(&self, lon: f64, lat: f64, local_from_body: &Mat3) -> Mat3 {
        (self.local_from_ecef * ecef_from_enu(lon, lat)).transpose() * local_from_body
    }

    /// Inverse of [`LocalFrame::body_rotation_from_navigation`]: (roll, pitch, true heading) in
    /// radians, heading in [0, 2π).
    pub fn navigation_from_body_rotation(&self, lon: f64, lat: f64, local_from_body: &Mat3) -> [f64; 3] {
        let ned_from_nav = self.local_from_ned(lon, lat).transpose() * local_from_body * NAV_BODY_FROM_BODY;
        let (roll, pitch, heading) = precimap_core::geom::rpy_from_rot(&ned_from_nav);
        [roll, pitch, heading.rem_euclid(std::f64::consts::TAU)]
    }
}

/// A field campaign's coordinates: the processing frame, and the CRS of its strip files.
#[derive(Clone, Debug)]
pub struct Georeference {
    pub frame: LocalFrame,
    pub strip_crs: Crs,
}

impl Georeference {
    /// Strip coordinates (grid of [`Georeference::strip_crs`]) → processing frame.
    pub fn local_from_strip(&self, p: [f64; 3]) -> Result<[f64; 3], CrsError> {
        let g = self.strip_crs.to_geographic(p)?;
        let g = self.frame.crs().geographic_from(&self.strip_crs, g)?;
        Ok(self.frame.local_from_geographic(g).into())
    }

    /// Processing frame → strip coordinates.
    pub fn strip_from_local(&self, p: [f64; 3]) -> Result<[f64; 3], CrsError> {
        let g = self.frame.geographic_from_local(&Vec3::from(p));
        let g = self.strip_crs.geographic_from(self.frame.crs(), g)?;
        self.strip_crs.from_geographic(g)
    }
}

/// The grid azimuth (clockwise from grid north, radians) of the meridian through (lon, lat):
/// central differences over ±1 µrad of latitude, accurate to ~1e-10 rad (rounding of the ~6 m
/// grid differences), i.e. 10 nm at 100 m.
fn grid_azimuth_of_north(crs: &Crs, lon: f64, lat: f64, h: f64) -> Result<f64, CrsError> {
    let d = 1e-6;
    let a = crs.from_geographic([lon, lat - d, h])?;
    let b = crs.from_geographic([lon, lat + d, h])?;
    Ok((b[0] - a[0]).atan2(b[1] - a[1]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use precimap_core::geom::{rot_from_rpy, rpy_from_rot};

    fn utm32() -> Crs {
        Crs::from_epsg(32632).unwrap()
    }

    /// The meridian arc from the equator to `lat` (numerical integration of M(φ) dφ), to check the
    /// projection against an independent formula: on the central meridian, N = k₀ · arc.
    fn meridian_arc(a: f64, e2: f64, lat: f64) -> f64 {
        let n = 200_000;
        let h = lat / n as f64;
        let m = |p: f64| a * (1.0 - e2) / (1.0 - e2 * p.sin().powi(2)).powf(1.5);
        // Simpson's rule.
        (0..n).map(|i| h / 6.0 * (m(i as f64 * h) + 4.0 * m((i as f64 + 0.5) * h) + m((i + 1) as f64 * h))).sum()
    }

    #[test]
    fn registry_names_and_kinds() {
        let c = utm32();
        assert_eq!(c.epsg(), 32632);
        assert_eq!(c.name(), "WGS 84 / UTM zone 32N");
        assert!(!c.is_geographic());
        assert!(c.wkt().starts_with("PROJCS[\"WGS 84 / UTM zone 32N\""));
        assert!(Crs::from_epsg(4979).unwrap().is_geographic());
        assert_eq!(Crs::from_epsg(25832).unwrap().name(), "ETRS89 / UTM zone 32N");
        assert!(matches!(Crs::from_epsg(99_999_999), Err(CrsError::Unknown(_))));
        assert!(matches!(Crs::from_epsg(4978), Err(CrsError::Unsupported { .. })), "geocentric");
        // US survey feet are refused, not silently read as metres.
        let feet = Crs::from_epsg(2227).unwrap_err().to_string();
        assert!(feet.contains("metre"), "{feet}");
        let e = LocalFrame::new(Crs::from_epsg(4326).unwrap(), [0.0; 3]).unwrap_err();
        assert!(e.to_string().contains("must be projected"), "{e}");
    }

    #[test]
    fn utm_matches_the_meridian_arc_and_its_central_meridian() {
        let c = utm32();
        let lat = 52.4f64.to_radians();
        let g = c.from_geographic([9f64.to_radians(), lat, 80.0]).unwrap();
        assert!((g[0] - 500_000.0).abs() < 1e-6, "{g:?}");
        assert_eq!(g[2], 80.0, "heights pass through");
        let want = 0.9996 * meridian_arc(6_378_137.0, c.e2, lat);
        assert!((g[1] - want).abs() < 1e-4, "{} vs {want}", g[1]);
        let back = c.to_geographic(g).unwrap();
        assert!((back[0] - 9f64.to_radians()).abs() < 1e-14 && (back[1] - lat).abs() < 1e-14, "{back:?}");
    }

    #[test]
    fn ecef_round_trip() {
        let c = utm32();
        for g in [[0.1, 0.9, 55.0], [-2.0, -0.7, -30.0], [3.0, 1.5, 8000.0]] {
            let x = c.ecef(g);
            let back = c.geodetic(&x);
            assert!((back[0] - g[0]).abs() < 1e-15 && (back[1] - g[1]).abs() < 1e-14, "{g:?} {back:?}");
            assert!((back[2] - g[2]).abs() < 1e-7, "{g:?} {back:?}");
        }
    }

    #[test]
    fn local_frame_is_metric_and_matches_the_grid_at_its_origin() {
        let origin = [549_800.0, 5_803_400.0, 55.0];
        let f = LocalFrame::new(utm32(), origin).unwrap();
        let o = f.local_from_grid(origin).unwrap();
        assert!((o - Vec3::from(origin)).norm() < 1e-8, "{o}");
        // Off the central meridian the convergence is Δλ·sin φ ≈ 0.57°.
        assert!((f.convergence_deg() - 0.57).abs() < 0.02, "{}", f.convergence_deg());
        // Round trips are exact to well below a micrometre over a few kilometres.
        for d in [[0.0, 0.0, 0.0], [1500.0, -800.0, 20.0], [-3000.0, 2500.0, -40.0]] {
            let g = [origin[0] + d[0], origin[1] + d[1], origin[2] + d[2]];
            let l = f.local_from_grid(g).unwrap();
            let back = f.grid_from_local(&l).unwrap();
            for k in 0..3 {
                assert!((back[k] - g[k]).abs() < 1e-7, "{g:?} → {back:?}");
            }
        }
        // Distances in the local frame are Earth-centred chord lengths; the grid's differ by its scale.
        let (a, b) = ([origin[0] - 500.0, origin[1], 55.0], [origin[0] + 500.0, origin[1], 55.0]);
        let (la, lb) = (f.local_from_grid(a).unwrap(), f.local_from_grid(b).unwrap());
        let chord = (f.ecef_from_local(&la) - f.ecef_from_local(&lb)).norm();
        assert!(((la - lb).norm() - chord).abs() < 1e-8);
        // UTM's scale 50 km off the central meridian, 0.9996·(1 + x²/2R²), times R/(R + 55 m).
        let scale = 1000.0 / chord;
        assert!((scale - 0.99962).abs() < 5e-6, "grid scale {scale}");
        // Near the origin, x/y follow grid east/north: a grid-east step stays on the local x axis.
        let east = f.local_from_grid([origin[0] + 10.0, origin[1], 55.0]).unwrap() - o;
        assert!(east.y.abs() < 1e-6 && (east.x - 10.0 / scale).abs() < 1e-6, "{east}");
    }

    #[test]
    fn navigation_attitude_turns_by_the_convergence() {
        let origin = [549_800.0, 5_803_400.0, 55.0];
        let f = LocalFrame::new(utm32(), origin).unwrap();
        let [lon, lat, _] = f.crs().to_geographic(origin).unwrap();
        // A level vehicle heading true north points along grid azimuth −γ: yaw (counter-clockwise
        // from grid east) 90° + γ. Yaw is 90° − heading + γ; pitch changes sign (nose up is
        // positive about the right axis, negative about the left one); roll keeps it.
        let r = f.body_rotation_from_navigation(lon, lat, 0.0, 0.0, 0.0);
        let (roll, pitch, yaw) = rpy_from_rot(&r);
        assert!(roll.abs() < 1e-12 && pitch.abs() < 1e-12, "{roll} {pitch}");
        assert!((yaw.to_degrees() - (90.0 + f.convergence_deg())).abs() < 1e-9, "{}", yaw.to_degrees());
        // Heading east, nose up 2°, right wing down 3°.
        let r = f.body_rotation_from_navigation(lon, lat, 3f64.to_radians(), 2f64.to_radians(), 90f64.to_radians());
        let (roll, pitch, yaw) = rpy_from_rot(&r);
        assert!((roll.to_degrees() - 3.0).abs() < 1e-9, "roll {}", roll.to_degrees());
        assert!((pitch.to_degrees() + 2.0).abs() < 1e-9, "pitch {}", pitch.to_degrees());
        assert!((yaw.to_degrees() - f.convergence_deg()).abs() < 1e-9, "yaw {}", yaw.to_degrees());
        // And back.
        let body = rot_from_rpy(0.01, -0.02, 1.3);
        let nav = f.navigation_from_body_rotation(lon + 0.01, lat - 0.003, &body);
        let again = f.body_rotation_from_navigation(lon + 0.01, lat - 0.003, nav[0], nav[1], nav[2]);
        assert!((again - body).norm() < 1e-14);
    }
}
