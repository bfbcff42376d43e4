//! The figures of the whole campaign from the strips' and trajectories' contributions.

use super::*;

/// Every trajectory's errors together, of the inputs and of the results.
pub(crate) fn totals(trajectories: &[(TrajectoryErrors, TrajectoryErrors)]) -> [TrajectoryErrors; 2] {
    let mut total = [TrajectoryErrors::default(); 2];
    for (b, a) in trajectories {
        total[0].merge(b);
        total[1].merge(a);
    }
    total
}

/// Every strip's contribution merged, in strip order.
struct StripTotals {
    before: ErrorStats,
    after: ErrorStats,
    tiles_before: TileStripMeans,
    tiles_after: TileStripMeans,
    shift_free_before: ShiftFreeMeans,
    shift_free_after: ShiftFreeMeans,
    classes: BTreeMap<u8, (ErrorStats, ErrorStats)>,
    class_means: [BTreeMap<u8, ShiftFreeMeans>; 2],
    class_surface_means: [ClassSurfaceStripMeans; 2],
    agreement: AgreementTally,
    per_strip: Vec<StripEvaluation>,
    points: u64,
    segment_tallies: Vec<SegmentTally>,
    assignment_tally: Option<AssignmentTally>,
    assignment_files: usize,
}

fn merge_strips(strip_jobs: &[(String, PathBuf)], strips: Vec<StripOutcome>) -> StripTotals {
    let mut t = StripTotals {
        before: ErrorStats::new(),
        after: ErrorStats::new(),
        tiles_before: TileStripMeans::new(),
        tiles_after: TileStripMeans::new(),
        shift_free_before: ShiftFreeMeans::new(),
        shift_free_after: ShiftFreeMeans::new(),
        classes: BTreeMap::new(),
        class_means: Default::default(),
        class_surface_means: Default::default(),
        agreement: AgreementTally::default(),
        per_strip: Vec::with_capacity(strips.len()),
        points: 0,
        segment_tallies: Vec::new(),
        assignment_tally: None,
        assignment_files: 0,
    };
    let StripTotals {
        before,
        after,
        tiles_before,
        tiles_after,
        shift_free_before,
        shift_free_after,
        classes,
        class_means,
        class_surface_means,
        agreement,
        per_strip,
        points,
        segment_tallies,
        assignment_tally,
        assignment_files,
    } = &mut t;
    for ((id, _), s) in strip_jobs.iter().zip(strips) {
        *points += s.points;
        if let Some(t) = s.assignments {
            *assignment_files += 1;
            assignment_tally.get_or_insert_with(AssignmentTally::default).merge(t);
        }
        if let Some(t) = s.segments {
            segment_tallies.push(t);
        }
        before.merge(&s.before);
        after.merge(&s.after);
        for (class, (b, a)) in &s.per_class {
            let c = classes.entry(*class).or_default();
            c.0.merge(b);
            c.1.merge(a);
        }
        tiles_before.merge(s.tiles_before);
        tiles_after.merge(s.tiles_after);
        shift_free_before.merge(s.shift_free_before);
        shift_free_after.merge(s.shift_free_after);
        for (total, part) in class_means.iter_mut().zip(s.classes) {
            for (class, means) in part {
                total.entry(class).or_default().merge(means);
            }
        }
        for (total, part) in class_surface_means.iter_mut().zip(s.class_surfaces) {
            total.merge(part);
        }
        agreement.merge(s.agreement);
        per_strip.push(StripEvaluation {
            id: id.clone(),
            points: s.points,
            surface_points: s.before.count(),
            rms_m: metric(s.before.rms(), s.after.rms()),
            mean_m: metric(s.before.mean(), s.after.mean()),
        });
    }
    t
}

/// The tiles whose strips disagree most after the adjustment, strips named by id.
fn worst_tiles(tiles_after: &TileStripMeans, per_strip: &[StripEvaluation]) -> Vec<TileDisagreement> {
    tiles_after
        .worst_tiles(SPREAD_MIN_POINTS, 8)
        .into_iter()
        .map(|(tile, rms_m, offsets)| TileDisagreement {
            tile: tile.to_string(),
            rms_m,
            offsets_m: offsets
                .into_iter()
                .map(|(k, o)| (per_strip.get(k as usize).map_or_else(|| format!("strip-{k}"), |s| s.id.clone()), o))
                .collect(),
        })
        .collect()
}

/// Each surface class's figures, by class name.
fn per_class(t: &StripTotals, campaign_shifts: [[f64; 3]; 2]) -> BTreeMap<String, ClassEvaluation> {
    let (class_means, class_surface_means) = (&t.class_means, &t.class_surface_means);
    t.classes
        .iter()
        .map(|(&class, (b, a))| {
            let name = SurfaceClass::from_u8(class).map_or_else(|| format!("class-{class}"), |c| c.name().to_string());
            let spread_without = |k: usize, d: [f64; 3]| {
                class_means[k].get(&class).map_or((f64::NAN, 0), |m| m.spread_without_shift(d, CLASS_SPREAD_MIN_POINTS))
            };
            let spread = |k: usize| spread_without(k, [0.0; 3]);
            let same_surface = |k: usize, d: [f64; 3]| {
                class_surface_means[k].spread_of_without_shift(CLASS_SPREAD_MIN_POINTS, |g| g.0 == class, d).0
            };
            let eval = ClassEvaluation {
                points: b.count(),
                rms_m: metric(b.rms(), a.rms()),
                mean_m: metric(b.mean(), a.mean()),
                p95_abs_m: metric(b.abs_quantile(0.95), a.abs_quantile(0.95)),
                spread_m: metric(spread(0).0, spread(1).0),
                same_surface_spread_m: metric(same_surface(0, [0.0; 3]), same_surface(1, [0.0; 3])),
                same_surface_spread_without_campaign_shift_m: metric(
                    same_surface(0, campaign_shifts[0]),
                    same_surface(1, campaign_shifts[1]),
                ),
                spread_without_campaign_shift_m: metric(
                    spread_without(0, campaign_shifts[0]).0,
                    spread_without(1, campaign_shifts[1]).0,
                ),
                tile_strip_pairs: spread(1).1,
            };
            (name, eval)
        })
        .collect()
}

/// Each trajectory's figures; `datum` and `attitude` are the campaign's mean position and
/// attitude errors, before and after.
fn per_trajectory(
    trajectory_jobs: &[(String, PathBuf)],
    trajectories: &[(TrajectoryErrors, TrajectoryErrors)],
    largest: &[[FrameLargest; 2]],
    [datum_before, datum_after]: [[f64; 3]; 2],
    [attitude_before, attitude_after]: [[f64; 3]; 2],
) -> Vec<TrajectoryEvaluation> {
    trajectory_jobs
        .iter()
        .zip(trajectories)
        .zip(largest)
        .map(|(((id, _), (b, a)), [largest_before, largest_after])| TrajectoryEvaluation {
            id: id.clone(),
            samples_before: b.samples,
            samples_after: a.samples,
            samples_outside_truth: b.outside_truth + a.outside_truth,
            position_rms_m: metric(b.position_rms_m(), a.position_rms_m()),
            rotation_rms_deg: metric(b.rotation_rms_deg(), a.rotation_rms_deg()),
            attitude_error_without_mean_rms_deg: AttitudeMetric::new(
                b.attitude.rms_without(attitude_before, b.length_m),
                a.attitude.rms_without(attitude_after, a.length_m),
            ),
            error_without_datum_rms_m: FrameMetric::new(
                b.frame.rms_without(datum_before, b.length_m),
                a.frame.rms_without(datum_after, a.length_m),
            ),
            largest_error_without_datum_before: *largest_before,
            largest_error_without_datum_after: *largest_after,
        })
        .collect()
}

pub(crate) fn assemble(
    strip_jobs: &[(String, PathBuf)],
    strips: Vec<StripOutcome>,
    trajectory_jobs: &[(String, PathBuf)],
    trajectories: Vec<(TrajectoryErrors, TrajectoryErrors)>,
    largest: &[[FrameLargest; 2]],
    points_used: Option<u64>,
) -> Evaluation {
    let t = merge_strips(strip_jobs, strips);
    let worst_tiles_after = worst_tiles(&t.tiles_after, &t.per_strip);
    let campaign_shifts = [t.shift_free_before.campaign_shift(), t.shift_free_after.campaign_shift()];
    let per_class = per_class(&t, campaign_shifts);
    let StripTotals {
        before,
        after,
        tiles_before,
        tiles_after,
        shift_free_before,
        shift_free_after,
        class_surface_means,
        agreement,
        per_strip,
        points,
        segment_tallies,
        assignment_tally,
        assignment_files,
        ..
    } = t;
    let (spread_before, pairs) = tiles_before.spread(SPREAD_MIN_POINTS);
    let (spread_after, _) = tiles_after.spread(SPREAD_MIN_POINTS);
    let (surface_spread_before, _) = class_surface_means[0].spread(SPREAD_MIN_POINTS);
    let (surface_spread_after, _) = class_surface_means[1].spread(SPREAD_MIN_POINTS);
    let [traj_before, traj_after] = totals(&trajectories);
    let (datum_before, datum_after) = (traj_before.mean_position_error_m(), traj_after.mean_position_error_m());
    let (attitude_before, attitude_after) =
        (traj_before.mean_rotation_error_deg(), traj_after.mean_rotation_error_deg());
    let per_trajectory = per_trajectory(
        trajectory_jobs,
        &trajectories,
        largest,
        [datum_before, datum_after],
        [attitude_before, attitude_after],
    );
    let surface_points = before.count();
    let segmentation = (!segment_tallies.is_empty() && segment_tallies.len() == strip_jobs.len())
        .then(|| SegmentEvaluation::from_tallies(&segment_tallies));
    let coplanar = if segmentation.is_some() { segments::coplanar_surfaces(&segment_tallies) } else { HashMap::new() };
    // Only when every strip has its file: a partial audit would mislead.
    let assignments = assignment_tally.filter(|_| assignment_files == strip_jobs.len()).map(|t| t.evaluate(&coplanar));
    let same_surface_agreement = agreement.evaluate(campaign_shifts, assignments.is_some());
    Evaluation {
        same_surface_agreement,
        segment_purity: segmentation.as_ref().map(|s| s.purity),
        surface_points_removed: segmentation.as_ref().map(|s| s.surface_points_removed),
        foliage_points_removed: segmentation.as_ref().map(|s| s.foliage_points_removed),
        segmentation,
        wrong_assignment_share: assignments.as_ref().map(|a| a.wrong_share),
        assignments,
        strip_offset_spread_m: metric(spread_before, spread_after),
        same_surface_spread_m: metric(surface_spread_before, surface_spread_after),
        same_surface_spread_without_campaign_shift_m: metric(
            class_surface_means[0].spread_of_without_shift(SPREAD_MIN_POINTS, |_| true, campaign_shifts[0]).0,
            class_surface_means[1].spread_of_without_shift(SPREAD_MIN_POINTS, |_| true, campaign_shifts[1]).0,
        ),
        spread_without_campaign_shift_m: metric(
            shift_free_before.spread_without_campaign_shift(SPREAD_MIN_POINTS).0,
            shift_free_after.spread_without_campaign_shift(SPREAD_MIN_POINTS).0,
        ),
        spread_without_tile_shift_m: metric(
            shift_free_before.spread_without_tile_shift(SPREAD_MIN_POINTS).0,
            shift_free_after.spread_without_tile_shift(SPREAD_MIN_POINTS).0,
        ),
        campaign_shift_m: VectorMetric {
            before: shift_free_before.campaign_shift(),
            after: shift_free_after.campaign_shift(),
        },
        datum_error_m: VectorMetric { before: datum_before, after: datum_after },
        spread_from_datum_m: metric(
            shift_free_before.spread_of_shift(datum_before, SPREAD_MIN_POINTS).0,
            shift_free_after.spread_of_shift(datum_after, SPREAD_MIN_POINTS).0,
        ),
        spread_from_local_datum_m: metric(
            shift_free_before.spread_of_local_datum(SPREAD_MIN_POINTS).0,
            shift_free_after.spread_of_local_datum(SPREAD_MIN_POINTS).0,
        ),
        surface_error_rms_m: metric(before.rms(), after.rms()),
        surface_error_mean_m: metric(before.mean(), after.mean()),
        surface_error_p95_abs_m: metric(before.abs_quantile(0.95), after.abs_quantile(0.95)),
        trajectory_error_rms_m: metric(traj_before.position_rms_m(), traj_after.position_rms_m()),
        trajectory_rotation_error_rms_deg: metric(traj_before.rotation_rms_deg(), traj_after.rotation_rms_deg()),
        trajectory_attitude_error_rms_deg: AttitudeMetric::new(
            traj_before.attitude.rms_without([0.0; 3], traj_before.length_m),
            traj_after.attitude.rms_without([0.0; 3], traj_after.length_m),
        ),
        mean_attitude_error_deg: VectorMetric { before: attitude_before, after: attitude_after },
        trajectory_attitude_error_without_mean_rms_deg: AttitudeMetric::new(
            traj_before.attitude.rms_without(attitude_before, traj_before.length_m),
            traj_after.attitude.rms_without(attitude_after, traj_after.length_m),
        ),
        trajectory_error_without_datum_rms_m: FrameMetric::new(
            traj_before.frame.rms_without(datum_before, traj_before.length_m),
            traj_after.frame.rms_without(datum_after, traj_after.length_m),
        ),
        trajectory_error_without_datum_unscanned_rms_m: None,
        trajectory_tilt_deg: metric(
            traj_before.tilt.plane().map_or(f64::NAN, |p| p.0),
            traj_after.tilt.plane().map_or(f64::NAN, |p| p.0),
        ),
        trajectory_vertical_error_without_tilt_rms_m: metric(
            traj_before.tilt.plane().map_or(f64::NAN, |p| p.1),
            traj_after.tilt.plane().map_or(f64::NAN, |p| p.1),
        ),
        surface_points_used_share: points_used.filter(|_| surface_points > 0).map(|u| u as f64 / surface_points as f64),
        points_used_last_iteration: points_used,
        tile_strip_pairs: pairs,
        worst_tiles_after,
        latent_map: None,
        latent_map_error_rms_m: None,
        latent_map_error_without_campaign_shift_rms_m: None,
        latent_map_error_without_tile_shift_rms_m: None,
        stated_precision: None,
        calibration: None,
        surface_points,
        points,
        strips: strip_jobs.len(),
        trajectory_samples: traj_after.samples,
        per_class,
        per_strip,
        per_trajectory,
    }
}
