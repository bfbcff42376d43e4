//! Rewrites a strip with the same points (positions, GPS times) but scan angles that follow no
//! rotating head: a pseudo-random angle per point, all on channel 0, as an unordered or merged
//! file might carry. For measuring preprocessing on a pattern the scan image does not recognise.
//!
//! `cargo run --release -p precimap-formats --example scramble_scan_angles -- IN.las OUT.las`

use precimap_formats::{read_strip, NewPoint, StripWriter};
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args_os().skip(1).map(PathBuf::from);
    let (Some(input), Some(output)) = (args.next(), args.next()) else {
        return Err("usage: scramble_scan_angles IN.las OUT.las".into());
    };
    let points = read_strip(&input)?;
    // Offsets near the points: 0.1 mm units must fit 32 bits.
    let offset = match points.len() {
        0 => [0.0; 3],
        _ => [points.x[0].round(), points.y[0].round(), points.z[0].round()],
    };
    let mut writer = StripWriter::create(&output, offset, 1e-4, "scrambled", "precimap example")?;
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    for k in 0..points.len() {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let angle = ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 180.0;
        writer.push(&NewPoint {
            position: [points.x[k], points.y[k], points.z[k]],
            gps_time: points.gps_time[k],
            scan_angle_deg: angle as f32,
            channel: 0,
            intensity: 100,
            return_number: 1,
            number_of_returns: 1,
            point_source_id: 1,
            classification: 0,
        })?;
    }
    let written = writer.finish()?;
    eprintln!("{}: {written} points", output.display());
    Ok(())
}
