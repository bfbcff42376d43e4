//! One strip's contribution: its points' errors before and after, against the truth.

use super::*;
use precimap_formats::StripPoints;
use precimap_sim::truth::TruthPoint;

/// Points whose result GPS time differs from the input's by more than this are out of order.
const GPS_TIME_TOLERANCE_S: f64 = 1e-6;

/// Everything one strip contributes.
#[derive(Debug)]
pub(crate) struct StripOutcome {
    pub(crate) points: u64,
    pub(crate) before: ErrorStats,
    pub(crate) after: ErrorStats,
    pub(crate) per_class: BTreeMap<u8, (ErrorStats, ErrorStats)>,
    pub(crate) tiles_before: TileStripMeans,
    pub(crate) tiles_after: TileStripMeans,
    pub(crate) segments: Option<SegmentTally>,
    pub(crate) assignments: Option<AssignmentTally>,
    /// All classes together: the per-class sums merged, plus the datum samples.
    pub(crate) shift_free_before: ShiftFreeMeans,
    pub(crate) shift_free_after: ShiftFreeMeans,
    /// Per class, and per (class, tile, surface), before and after. A surface id has one class,
    /// so the latter also gives the whole campaign's same-surface spread.
    pub(crate) classes: [BTreeMap<u8, ShiftFreeMeans>; 2],
    pub(crate) class_surfaces: [ClassSurfaceStripMeans; 2],
    pub(crate) agreement: AgreementTally,
    /// The first and last GPS time of the strip's points; `None` without points.
    pub(crate) time_span: Option<(f64, f64)>,
}

fn result_strip_path(result_dir: &Path, id: &str) -> Result<PathBuf, EvalError> {
    let las = result_dir.join("strips").join(format!("{id}.las"));
    let laz = result_dir.join("strips").join(format!("{id}.laz"));
    if las.is_file() {
        Ok(las)
    } else if laz.is_file() {
        Ok(laz)
    } else {
        Err(EvalError::MissingResultStrip { strip: id.to_string(), las, laz })
    }
}

pub(crate) fn evaluate_strip(
    id: &str,
    index: u32,
    input: &Path,
    trajectory: Option<&LoadedTrajectory>,
    truth_dir: &Path,
    result_dir: &Path,
) -> Result<StripOutcome, EvalError> {
    let truth_path = truth_dir.join(format!("{id}.truth"));
    let mut truth = TruthReader::open(&truth_path)?;
    let expected = truth.len();
    let count_error = |which, path: &Path, found: usize| EvalError::PointCount {
        strip: id.to_string(),
        which,
        path: path.to_path_buf(),
        truth: truth_path.clone(),
        found: found as u64,
        expected,
    };
    // Cheap checks first: a missing result should not cost reading the input.
    let result_path = result_strip_path(result_dir, id)?;
    let before = read_strip(input)?;
    if before.len() as u64 != expected {
        return Err(count_error("input", input, before.len()));
    }
    let after = read_strip(&result_path)?;
    if after.len() as u64 != expected {
        return Err(count_error("result", &result_path, after.len()));
    }
    if let Some(i) = (0..after.len()).find(|&i| (after.gps_time[i] - before.gps_time[i]).abs() > GPS_TIME_TOLERANCE_S) {
        return Err(EvalError::PointOrder {
            strip: id.to_string(),
            path: result_path,
            index: i,
            found: after.gps_time[i],
            expected: before.gps_time[i],
        });
    }

    let mut out = StripOutcome {
        points: expected,
        before: ErrorStats::new(),
        after: ErrorStats::new(),
        per_class: BTreeMap::new(),
        tiles_before: TileStripMeans::new(),
        tiles_after: TileStripMeans::new(),
        segments: None,
        assignments: None,
        shift_free_before: ShiftFreeMeans::new(),
        shift_free_after: ShiftFreeMeans::new(),
        classes: Default::default(),
        class_surfaces: Default::default(),
        agreement: AgreementTally::default(),
        time_span: before.gps_time_span(),
    };
    // Per-point id files next to the result (optional), each checked against the point count.
    let per_point_ids =
        |folder: &str, extension: &str, which: &'static str, read: fn(&Path) -> Result<Vec<u32>, FormatError>| {
            let path = result_dir.join(folder).join(format!("{id}.{extension}"));
            if !path.is_file() {
                return Ok(None);
            }
            let ids = read(&path)?;
            if ids.len() as u64 != expected {
                return Err(count_error(which, &path, ids.len()));
            }
            Ok(Some(ids))
        };
    let segment_ids = per_point_ids("segments", "seg", "segment", precimap_formats::read_segments)?;
    let assignment_ids = per_point_ids("assignments", "asg", "assignment", precimap_formats::read_assignments)?;
    let mut tally = SegmentTally::default();
    let mut assigned = AssignmentTally::default();
    // Per trajectory (truth, input, result), the segment the last point's time fell in.
    let mut segment_hints = [0usize; 3];
    let mut i = 0usize;
    while let Some(t) = truth.next_point()? {
        let k = i;
        i += 1;
        if let Some(ids) = &segment_ids {
            tally.add(ids[k], t.surface_id, t.class, t.normal, t.position);
        }
        if let Some(ids) = &assignment_ids {
            assigned.add(ids[k], t.surface_id, t.class);
        }
        if !t.class.is_surface() {
            continue;
        }
        let assigned = assignment_ids.as_ref().is_some_and(|ids| ids[k] != u32::MAX);
        let point = SurfacePoint { k, truth: &t, index, trajectory, assigned };
        add_surface_point(&mut out, &before, &after, &point, &truth_path, id, &mut segment_hints)?;
    }
    for class in out.classes[0].values() {
        out.shift_free_before.merge(class.clone());
    }
    for class in out.classes[1].values() {
        out.shift_free_after.merge(class.clone());
    }
    out.segments = segment_ids.map(|_| tally);
    out.assignments = assignment_ids.map(|_| assigned);
    Ok(out)
}

/// One surface point of a strip: its index `k`, its truth, the strip's index, its trajectory,
/// and whether the last map pass assigned it.
struct SurfacePoint<'a> {
    k: usize,
    truth: &'a TruthPoint,
    index: u32,
    trajectory: Option<&'a LoadedTrajectory>,
    assigned: bool,
}

/// Adds surface point `p.k` of the strip `id` (its input `before`, its result `after`) to `out`.
fn add_surface_point(
    out: &mut StripOutcome,
    before: &StripPoints,
    after: &StripPoints,
    p: &SurfacePoint<'_>,
    truth_path: &Path,
    id: &str,
    segment_hints: &mut [usize; 3],
) -> Result<(), EvalError> {
    let (k, t, index, trajectory) = (p.k, p.truth, p.index, p.trajectory);
    let pb = [before.x[k], before.y[k], before.z[k]];
    let pa = [after.x[k], after.y[k], after.z[k]];
    let bad_normal = || EvalError::BadNormal {
        strip: id.to_string(),
        path: truth_path.to_path_buf(),
        index: k as u64,
        normal: t.normal,
    };
    let eb = signed_normal_error(pb, t.position, t.normal).ok_or_else(bad_normal)?;
    let ea = signed_normal_error(pa, t.position, t.normal).ok_or_else(bad_normal)?;
    out.before.add(eb);
    out.after.add(ea);
    let class = out.per_class.entry(t.class as u8).or_default();
    class.0.add(eb);
    class.1.add(ea);
    let tile = TileKey::of(t.position[0], t.position[1], SPREAD_TILE_M);
    out.tiles_before.add(tile, index, eb);
    out.tiles_after.add(tile, index, ea);
    let len = t.normal.iter().map(|&c| (c as f64).powi(2)).sum::<f64>().sqrt();
    let unit = t.normal.map(|c| c as f64 / len);
    let travel = trajectory.and_then(|tr| tr.truth.pose_at(before.gps_time[k])).map(|p| {
        let x = p.rotation.column(0);
        [x[0], x[1], x[2]]
    });
    let orientation = Orientation::of(unit, travel) as u8;
    for (k, e) in [eb, ea].into_iter().enumerate() {
        out.classes[k].entry(t.class as u8).or_default().add(tile, index, e, unit);
        out.class_surfaces[k].add_oriented((t.class as u8, tile, t.surface_id), index, e, unit);
        out.agreement.means[k].add_oriented((orientation, tile, t.surface_id), index, e, unit);
    }
    out.agreement.points[orientation as usize] += 1;
    if p.assigned {
        out.agreement.used[orientation as usize] += 1;
    }
    if let Some(tr) = trajectory {
        let time = before.gps_time[k];
        if let Some(truth_position) = tr.truth.position_at_from(time, &mut segment_hints[0]) {
            if let Some(g) = position_error_from(&tr.input, truth_position, time, &mut segment_hints[1]) {
                out.shift_free_before.add_datum_sample(tile, g);
            }
            if let Some(g) = position_error_from(&tr.result, truth_position, time, &mut segment_hints[2]) {
                out.shift_free_after.add_datum_sample(tile, g);
            }
        }
    }
    Ok(())
}
