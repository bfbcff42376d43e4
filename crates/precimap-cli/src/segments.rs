//! `precimap segments STRIP --png OUT.png`: segments one strip and draws its scan image with a
//! random colour per segment (the paper's Figures 3–4): rows = measurement within a revolution
//! (top = scan angle −180°), columns = revolutions. Black: no return; grey: in no segment (no
//! normal or a removed small region); dark blue: revolutions dropped at standstill.

use anyhow::{bail, Context, Result};
use precimap_estimate::{SegmentParams, DROPPED_SEGMENT, NO_SEGMENT};
use precimap_pipeline::{tasks, Campaign};
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct SegmentsArgs {
    /// The strip: its file (as the manifest names it) or its id.
    pub strip: String,
    /// The campaign manifest (default: `manifest.json` in the strip's folder or the one above).
    #[arg(long)]
    pub manifest: Option<PathBuf>,
    /// Write the scan image with random segment colours here.
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Only draw revolutions FIRST:LAST (image columns).
    #[arg(long)]
    pub columns: Option<String>,
    /// Regions with fewer points are removed.
    #[arg(long)]
    pub min_region_points: Option<u32>,
    /// Felzenszwalb–Huttenlocher k.
    #[arg(long)]
    pub fh_k: Option<f64>,
    /// Least-squares normals instead of RANSAC (for comparison).
    #[arg(long)]
    pub least_squares: bool,
    /// Write the per-point segment ids here (the `OUT/segments/{strip}.seg` format).
    #[arg(long)]
    pub ids: Option<PathBuf>,
    /// Print the statistics as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: SegmentsArgs) -> Result<()> {
    let strip_path = Path::new(&args.strip);
    let manifest = match &args.manifest {
        Some(m) => m.clone(),
        None => {
            let dir = strip_path.parent().unwrap_or(Path::new("."));
            [dir.join("manifest.json"), dir.join("..").join("manifest.json")]
                .into_iter()
                .find(|p| p.is_file())
                .with_context(|| format!("no manifest.json next to or above {}; pass --manifest", args.strip))?
        }
    };
    let campaign = Campaign::load(&manifest).with_context(|| format!("loading {}", manifest.display()))?;
    let wanted = std::fs::canonicalize(strip_path).ok();
    let index = campaign
        .strips
        .iter()
        .position(|s| s.id == args.strip || (wanted.is_some() && std::fs::canonicalize(&s.path).ok() == wanted))
        .with_context(|| format!("{} names no strip of {}", args.strip, manifest.display()))?;
    let mut params = SegmentParams::default();
    if let Some(n) = args.min_region_points {
        params.min_region_points = n;
    }
    if let Some(k) = args.fh_k {
        params.fh_k = k;
    }
    if args.least_squares {
        params.method = precimap_estimate::NormalMethod::LeastSquares;
    }
    let started = std::time::Instant::now();
    let prepared = tasks::prepare_strip_in_memory(&campaign, index, &params)?;
    let seconds = started.elapsed().as_secs_f64();
    let stats = &prepared.stats;
    if args.json {
        outln!(
            "{}",
            serde_json::json!({ "strip": campaign.strips[index].id, "seconds": seconds, "params": params, "stats": stats })
        );
    } else {
        let s = &stats.segmentation;
        eprintln!(
            "strip {}: {} points, image {} rows × {} revolutions; {} with a normal, {} regions, {} segments \
             holding {} points ({:.1} %), {} points in removed small regions ({:.2} s)",
            campaign.strips[index].id,
            stats.points,
            stats.rows_per_revolution,
            stats.revolutions,
            s.points_with_normal,
            s.regions,
            s.segments,
            s.points_segmented,
            100.0 * s.points_segmented as f64 / stats.points.max(1) as f64,
            s.points_in_small_regions,
            seconds
        );
    }
    if let Some(path) = &args.ids {
        std::fs::write(path, precimap_formats::encode_segments(&prepared.segment))
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(png) = &args.png {
        let range = match &args.columns {
            None => None,
            Some(r) => {
                let (a, b) = r.split_once(':').context("--columns takes FIRST:LAST")?;
                let (a, b): (u32, u32) = (a.trim().parse()?, b.trim().parse()?);
                if b < a {
                    bail!("--columns {r}: LAST is before FIRST");
                }
                Some((a, b))
            }
        };
        write_png(png, &prepared, range).with_context(|| format!("writing {}", png.display()))?;
        eprintln!("scan image: {}", png.display());
    }
    Ok(())
}

/// A bright colour per segment id (a fixed hash, so the same id always gets the same colour).
fn colour(id: u32) -> [u8; 3] {
    let mut x = (id as u64).wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^= x >> 31;
    [(64 + (x & 0xBF)) as u8, (64 + ((x >> 8) & 0xBF)) as u8, (64 + ((x >> 16) & 0xBF)) as u8]
}

fn write_png(path: &Path, prepared: &precimap_estimate::PreparedStrip, range: Option<(u32, u32)>) -> Result<()> {
    let Some(image) = &prepared.image else {
        bail!("the strip's normals came from 3-D neighbours (its scan pattern makes no scan image): there is no image to draw");
    };
    let (first, last) = range.unwrap_or((0, image.columns.saturating_sub(1)));
    let last = last.min(image.columns.saturating_sub(1));
    if first > last {
        bail!("the strip has {} revolutions; nothing to draw in {first}:{last}", image.columns);
    }
    let width = (last - first + 1) as usize;
    let height = image.rows as usize;
    let mut rgb = vec![0u8; width * height * 3];
    // Dropped revolutions have no column: draw them where their neighbours' columns are unknown,
    // i.e. count them separately.
    for (k, &id) in prepared.segment.iter().enumerate() {
        let c = image.column[k];
        if c == precimap_estimate::DROPPED_COLUMN || c < first || c > last {
            continue;
        }
        let px = (image.row[k] as usize * width + (c - first) as usize) * 3;
        let col = match id {
            NO_SEGMENT => [110, 110, 110],
            DROPPED_SEGMENT => [20, 20, 90],
            id => colour(id),
        };
        rgb[px..px + 3].copy_from_slice(&col);
    }
    let file = std::fs::File::create(path)?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), width as u32, height as u32);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header()?;
    writer.write_image_data(&rgb)?;
    writer.finish()?;
    Ok(())
}
