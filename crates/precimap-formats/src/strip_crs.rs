//! The CRS a LAS/LAZ file declares in its VLRs (OGC WKT, record 2112, or GeoTIFF keys, record
//! 34735), and the VLR that declares one.

use crate::FormatError;
use las::{Builder, Header, Version, Vlr};
use std::fmt;
use std::path::Path;

/// A strip's declared CRS.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StripCrs {
    /// The horizontal CRS's EPSG code, when the declaration names one.
    pub epsg: Option<u32>,
    /// How it is declared, for messages: `WKT "ETRS89 / UTM zone 32N"` or `GeoTIFF keys`.
    pub declared_as: String,
    pub wkt: bool,
}

impl fmt::Display for StripCrs {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.epsg {
            Some(code) => write!(f, "EPSG:{code} ({})", self.declared_as),
            None => write!(f, "{} without an EPSG code", self.declared_as),
        }
    }
}

/// The byte span `[start, end)` of the first bracketed WKT node whose keyword is one of `keywords`.
fn node<'a>(wkt: &'a str, keywords: &[&str]) -> Option<&'a str> {
    let start = keywords.iter().filter_map(|k| wkt.find(&format!("{k}[")).map(|i| (i, k.len()))).min()?;
    let open = start.0 + start.1;
    let mut depth = 0usize;
    for (i, c) in wkt[open..].char_indices() {
        match c {
            '[' => depth += 1,
            ']' => {
                depth -= 1;
                if depth == 0 {
                    return Some(&wkt[start.0..open + i + 1]);
                }
            }
            _ => {}
        }
    }
    None
}

/// The EPSG code of a WKT node: its own (last, outermost) `AUTHORITY["EPSG","n"]` or `ID["EPSG",n]`.
fn node_epsg(node: &str) -> Option<u32> {
    let tail = node.rfind("AUTHORITY[\"EPSG\"").or_else(|| node.rfind("ID[\"EPSG\""))?;
    let rest = &node[tail..];
    let comma = rest.find(',')?;
    let digits: String = rest[comma + 1..].chars().filter(|c| *c != '"').take_while(char::is_ascii_digit).collect();
    digits.parse().ok()
}

/// The horizontal CRS's name and EPSG code of a WKT (1 or 2): the projected CRS if there is one,
/// else the geographic one (inside a compound CRS too).
pub fn wkt_horizontal(wkt: &str) -> (Option<String>, Option<u32>) {
    let n = node(wkt, &["PROJCS", "PROJCRS", "PROJECTEDCRS"])
        .or_else(|| node(wkt, &["GEOGCS", "GEOGCRS", "GEOGRAPHICCRS"]));
    let Some(n) = n else { return (None, None) };
    let name = n.split_once("[\"").and_then(|(_, r)| r.split_once('"')).map(|(name, _)| name.to_string());
    (name, node_epsg(n))
}

/// The CRS `header` declares, if any.
pub fn header_crs(header: &Header) -> Option<StripCrs> {
    if let Some(bytes) = header.get_wkt_crs_bytes() {
        let text = String::from_utf8_lossy(bytes);
        let text = text.trim_end_matches('\0');
        let (name, epsg) = wkt_horizontal(text);
        return Some(StripCrs {
            epsg,
            declared_as: format!("WKT {:?}", name.unwrap_or_else(|| "unnamed".into())),
            wkt: true,
        });
    }
    if !header.has_crs_vlrs() {
        return None;
    }
    // Damaged keys read as a declaration without a code (refused where a CRS is checked).
    let keys = header.get_geotiff_crs().ok().flatten();
    let projected = keys.as_ref().and_then(|k| k.get_projected_crs_geo_key_value());
    let geodetic = keys.as_ref().and_then(|k| k.get_geodetic_crs_geo_key_value());
    // 32767 is GeoTIFF's "user-defined".
    let epsg = projected.or(geodetic).filter(|c| *c != 32767).map(u32::from);
    Some(StripCrs { epsg, declared_as: "GeoTIFF keys".into(), wkt: false })
}

/// A GeoKeyDirectory VLR naming a projected CRS in metres.
pub fn geotiff_vlr(epsg: u16) -> Vlr {
    // Version 1.1.0, 4 keys: model type projected, raster type pixel-is-area, projected CRS, metres.
    let words: [u16; 20] = [1, 1, 0, 4, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, epsg, 3076, 0, 1, 9001];
    Vlr {
        user_id: "LASF_Projection".into(),
        record_id: 34735,
        description: "GeoKeyDirectoryTag".into(),
        data: words.iter().flat_map(|w| w.to_le_bytes()).collect(),
    }
}

/// A CRS for [`rewrite_strip_declaring`]: its EPSG code and WKT.
#[derive(Clone, Copy, Debug)]
pub struct DeclaredCrs<'a> {
    pub epsg: u32,
    pub wkt: &'a str,
}

/// What a new strip declares besides its points.
#[derive(Clone, Copy, Debug, Default)]
pub struct StripDeclarations<'a> {
    /// The CRS's OGC WKT, written as a WKT VLR.
    pub wkt: Option<&'a str>,
    /// GPS times are adjusted standard GPS time (global-encoding bit 0), not week seconds.
    pub adjusted_standard_time: bool,
}

pub(crate) fn declare_crs(src: &Path, header: &mut Header, crs: DeclaredCrs<'_>) -> Result<(), FormatError> {
    if header_crs(header).is_some() {
        return Ok(());
    }
    let refused = |e: String| FormatError::file(src, format!("cannot declare EPSG:{} in the copy: {e}", crs.epsg));
    if header.version() >= Version::new(1, 4) {
        header.set_wkt_crs(crs.wkt.as_bytes().to_vec()).map_err(|e| refused(e.to_string()))
    } else {
        let code = u16::try_from(crs.epsg).map_err(|_| refused("GeoTIFF keys hold codes up to 65535".into()))?;
        let mut b = Builder::from(header.clone());
        b.vlrs.push(geotiff_vlr(code));
        *header = b.into_header().map_err(|e| refused(e.to_string()))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wkt1_wkt2_and_compound() {
        let utm = crs_definitions::EPSG_32632.wkt;
        assert_eq!(wkt_horizontal(utm), (Some("WGS 84 / UTM zone 32N".into()), Some(32632)));
        let geo3d = crs_definitions::EPSG_4979.wkt;
        assert_eq!(wkt_horizontal(geo3d).1, Some(4979));
        let compound = format!(
            "COMPD_CS[\"ETRS89 / UTM 32N + DHHN2016\",{},VERT_CS[\"DHHN2016 height\",VERT_DATUM[\"x\",2005],AUTHORITY[\"EPSG\",\"7837\"]],AUTHORITY[\"EPSG\",\"4647\"]]",
            crs_definitions::EPSG_25832.wkt
        );
        assert_eq!(wkt_horizontal(&compound).1, Some(25832));
        assert_eq!(wkt_horizontal("LOCAL_CS[\"x\"]"), (None, None));
        assert_eq!(wkt_horizontal("PROJCS[\"broken\""), (None, None));
    }

    #[test]
    fn geotiff_keys_and_wkt_headers() {
        let mut b = las::Builder::from(las::Version::new(1, 2));
        b.vlrs.push(geotiff_vlr(25832));
        let c = header_crs(&b.into_header().unwrap()).unwrap();
        assert_eq!((c.epsg, c.wkt), (Some(25832), false));
        assert_eq!(c.to_string(), "EPSG:25832 (GeoTIFF keys)");
        let mut h = las::Builder::from(las::Version::new(1, 4)).into_header().unwrap();
        assert_eq!(header_crs(&h), None);
        h.set_wkt_crs(crs_definitions::EPSG_32632.wkt.as_bytes().to_vec()).unwrap();
        let c = header_crs(&h).unwrap();
        assert_eq!(c.to_string(), "EPSG:32632 (WKT \"WGS 84 / UTM zone 32N\")");
    }
}
