use super::models::*;
use super::point::*;
use super::pulls::*;
use super::raster::*;
use super::triangles::*;
use super::*;
use crate::blocks::{IntervalMoments, TrajectoryBlocks};
use crate::chunk::NO_NEIGHBOUR;

fn patch(strip: u32, anchor: u32, normal: [f64; 3], centre: [f64; 3], count: u32) -> Patch {
    let c = count as f64;
    Patch { cell: 7, strip, anchor, sum_normal: normal.map(|v| v * c), sum_position: centre.map(|v| v * c), count }
}

/// Road and sidewalk of one pass never share a model; another strip's road and sidewalk each
/// join the nearest plane; a coplanar second segment of the same pass joins; an opposite
/// normal never does.
#[test]
fn patches_join_by_pass_normal_and_plane_distance() {
    let up = [0.0, 0.0, 1.0];
    let patches = [
        patch(0, 10, up, [0.5, 0.5, 0.0], 100),               // 0: strip 0 road
        patch(0, 10, up, [0.5, 0.9, 0.12], 50),               // 1: strip 0 sidewalk, 12 cm up
        patch(1, 500, up, [0.4, 0.5, 0.02], 90),              // 2: strip 1 road, 2 cm off
        patch(1, 500, up, [0.4, 0.9, 0.135], 40),             // 3: strip 1 sidewalk
        patch(0, 11, up, [0.8, 0.2, 0.01], 30),               // 4: strip 0, road split by an occlusion
        patch(1, 500, [0.0, 0.0, -1.0], [0.5, 0.5, 0.0], 20), // 5: underside
    ];
    let m = join_patches(&patches, 30f64.to_radians().cos(), 0.1);
    assert_eq!(m[2], m[0]);
    assert_eq!(m[4], m[0]);
    assert_ne!(m[1], m[0]);
    assert_eq!(m[3], m[1]);
    assert!(m[5] != m[0] && m[5] != m[1]);
}

/// A strip scanning a tilted plane (0.5 m × 0.1 m grid of points, scan-image links) `offset`
/// metres above it, from a head 3 m above at the given x.
fn plane_strip(tile: TileKey, strip: u32, offset: f64, shift: [f64; 2]) -> TileChunk {
    plane_strip_every(tile, strip, offset, shift, 1)
}

/// [`plane_strip`] with `per_row` times as many revolutions (rows), as a slower pass has.
fn plane_strip_every(tile: TileKey, strip: u32, offset: f64, shift: [f64; 2], per_row: usize) -> TileChunk {
    let height = |x: f64, y: f64| 0.05 * x - 0.03 * y + offset;
    strip_on(tile, strip, shift, per_row, height, normalize([-0.05, 0.03, 1.0]))
}

/// A strip scanning the plane `z = height(x, y)` of normal `n` (see [`plane_strip`]).
fn strip_on(
    tile: TileKey,
    strip: u32,
    shift: [f64; 2],
    per_row: usize,
    height: impl Fn(f64, f64) -> f64,
    n: [f64; 3],
) -> TileChunk {
    strip_through(tile, strip, shift, per_row, n, |x, y| ([x, 2.0, 3.0], [x, y, height(x, y)]))
}

/// A strip of 40 × `per_row` revolutions of 12 points on a surface of normal `n`: `at(u, v)`
/// gives the head and the point for revolution coordinate `u` (0.1 m apart, from 2 m +
/// `shift[0]`) and point coordinate `v` (0.5 m apart, from 2 m + `shift[1]`).
fn strip_through(
    tile: TileKey,
    strip: u32,
    shift: [f64; 2],
    per_row: usize,
    n: [f64; 3],
    at: impl Fn(f64, f64) -> ([f64; 3], [f64; 3]),
) -> TileChunk {
    let (cols, rows) = (12usize, 40 * per_row);
    let mut c = TileChunk::with_capacity(tile, strip, strip, [0.0, 0.0, 0.0], cols * rows);
    for row in 0..rows {
        for col in 0..cols {
            let (u, v) = (2.0 + shift[0] + 0.1 * row as f64 / per_row as f64, 2.0 + shift[1] + 0.5 * col as f64);
            let (head, p) = at(u, v);
            c.t0.push(head.map(|v| v as f32));
            c.r.push([(p[0] - head[0]) as f32, (p[1] - head[1]) as f32, (p[2] - head[2]) as f32]);
            c.normal.push(n.map(|v| v as f32));
            c.anchor.push((row / (5 * per_row)) as u32);
            c.lambda.push((row % (5 * per_row)) as f32 / (5 * per_row) as f32);
            let k = row * cols + col;
            c.right.push(if col + 1 < cols { (k + 1) as u32 } else { NO_NEIGHBOUR });
            c.down.push(if row + 1 < rows { (k + cols) as u32 } else { NO_NEIGHBOUR });
            c.edge_limit.push(1.0);
            c.segment.push(0);
            c.source.push(k as u32);
        }
    }
    c
}

/// Two passes 4 cm apart on either side of a 1 m cell face (z = 1 m) across their surface
/// still meet in one model per cell with segments: cells are columns along the normal.
/// Cubic cells (grouping by normal alone) put the passes in two cells that never meet, and
/// that disagreement would persist.
#[test]
fn passes_either_side_of_a_cell_face_meet_in_one_model() {
    let tile = TileKey { tx: 0, ty: 0 };
    let up = [0.0, 0.0, 1.0];
    let chunks =
        [strip_on(tile, 0, [0.0, 0.0], 1, |_, _| 0.98, up), strip_on(tile, 1, [0.033, 0.21], 1, |_, _| 1.02, up)];
    let corrections = vec![TrajectoryCorrections::zeros(0, 8); 2];
    let step = IterationStep::new(0.01, 0.05);
    let run = |segment_surfaces: bool| {
        let params = Parameters { segment_surfaces, point_latent_below_grid_m: 0.02, ..Default::default() };
        estimate_tile(tile, &chunks, &corrections, &params, &step, &[]).unwrap()
    };
    let columns = run(true);
    assert!(columns.stats.points_used > 500, "{}", columns.stats.points_used);
    // The passes meet in the middle: every residual is ±2 cm, and the pulls are opposite.
    let rms = (columns.stats.residual_sum2_m2 / columns.stats.points_used as f64).sqrt();
    assert!((rms - 0.02).abs() < 1e-3, "{rms}");
    let pull = |t: &TrajectoryBlocks| t.blocks.iter().map(|b| b.rhs[2]).sum::<f64>();
    assert!(pull(&columns.blocks[0]) > 1.0 && pull(&columns.blocks[1]) < -1.0);
    // Each cubic cell the strips cross holds one pass only: twice the models, no observation.
    let cubes = run(false);
    assert_eq!(cubes.stats.surface_models, 2 * columns.stats.surface_models);
    assert_eq!(cubes.stats.points_used, 0);
}

/// A capture step's cells are columns along the normal too. Two passes 10 cm apart on either
/// side of a façade parallel to a 3 m cell face (x = 9 m) meet in one model per cell; in
/// vertical columns they fell into two cells that never met, and small s3
/// at a 0.3° step kept one street's passes in two groups 0.3 m apart along the track.
#[test]
fn capture_passes_either_side_of_a_cell_face_meet_in_one_model() {
    let tile = TileKey { tx: 0, ty: 0 };
    let facing_the_street = [-1.0, 0.0, 0.0];
    let facade = |strip: u32, x: f64| {
        strip_through(tile, strip, [0.0, 0.0], 1, facing_the_street, |u, v| ([x - 6.0, u, 1.5], [x, u, v]))
    };
    let chunks = [facade(0, 8.95), facade(1, 9.05)];
    let corrections = vec![TrajectoryCorrections::zeros(0, 8); 2];
    let step =
        IterationStep { cell_m: Some(3.0), column_cells: true, rotation: false, ..IterationStep::new(0.25, 1.0) };
    for segment_surfaces in [true, false] {
        let params = Parameters { segment_surfaces, ..Default::default() };
        let estimate = estimate_tile(tile, &chunks, &corrections, &params, &step, &[]).unwrap();
        assert!(estimate.stats.points_used > 500, "{segment_surfaces}: {}", estimate.stats.points_used);
        // They meet in the middle: every residual is ±5 cm, and the pulls across the façade
        // are opposite.
        let rms = (estimate.stats.residual_sum2_m2 / estimate.stats.points_used as f64).sqrt();
        assert!((rms - 0.05).abs() < 1e-3, "{segment_surfaces}: {rms}");
        let pull = |t: &TrajectoryBlocks| t.blocks.iter().map(|b| b.rhs[0]).sum::<f64>();
        let (near, far) = (pull(&estimate.blocks[0]), pull(&estimate.blocks[1]));
        assert!(near * far < 0.0 && near.abs() > 1.0, "{segment_surfaces}: {near} {far}");
    }
}

/// A triangle whose corners its pass's segmentation split must not give a latent height:
/// across a 12 cm step seen at 0.5 m spacing (a facet 13.5° off level, within the facet
/// test) it puts the points of the other pass under it 2.5 cm off their surface. With the
/// step a segment break, the two noise-free passes agree exactly wherever they are observed;
/// with the step inside one segment, the bridges' residuals appear.
#[test]
fn triangles_do_not_bridge_segment_breaks() {
    let tile = TileKey { tx: 0, ty: 0 };
    let step_y = 4.3;
    let height = |_: f64, y: f64| if y < step_y { 0.0 } else { 0.12 };
    let with_segments = |mut c: TileChunk, split: bool| {
        for k in 0..c.len() {
            let y = c.t0[k][1] as f64 + c.r[k][1] as f64;
            c.segment[k] = (split && y >= step_y) as u32;
        }
        c
    };
    // Both routes: exact sampling at the points, and at pixel centres.
    for share in [0.0, 0.7] {
        let run = |split: bool| {
            let up = [0.0, 0.0, 1.0];
            let chunks = [
                with_segments(strip_on(tile, 0, [0.0, 0.0], 1, height, up), split),
                with_segments(strip_on(tile, 1, [0.033, 0.21], 1, height, up), split),
            ];
            fine_pass_stats_on(tile, &chunks, 0.05, 0.0, share)
        };
        let rms = |s: &TileStats| (s.residual_sum2_m2 / s.points_used as f64).sqrt();
        let (split, merged) = (run(true), run(false));
        assert!(split.points_used > 500, "share {share}: {}", split.points_used);
        assert!(rms(&split) < 1e-5, "share {share}: {}", rms(&split));
        // One pass's points beside the step sit under the other's bridges: 2.5 cm residuals.
        assert!(merged.points_used > split.points_used, "share {share}");
        assert!(rms(&merged) > 5e-3, "share {share}: {}", rms(&merged));
    }
}

/// One point-sampled 1 cm pass over `chunks` on the exact route with the given outlier
/// threshold and [`Parameters::cover_agreement_thresholds`].
fn fine_pass_stats(tile: TileKey, chunks: &[TileChunk], threshold: f64, gate: f64) -> TileStats {
    fine_pass_stats_on(tile, chunks, threshold, gate, 0.0)
}

/// [`fine_pass_stats`] with [`Parameters::latent_pixel_share`] (0: the exact route).
fn fine_pass_stats_on(tile: TileKey, chunks: &[TileChunk], threshold: f64, gate: f64, share: f64) -> TileStats {
    let corrections = vec![TrajectoryCorrections::zeros(0, 8); chunks.len()];
    let step = IterationStep::new(0.01, threshold);
    let params = Parameters {
        point_latent_below_grid_m: 0.02,
        cover_agreement_thresholds: gate,
        latent_pixel_share: share,
        ..Default::default()
    };
    estimate_tile(tile, chunks, &corrections, &params, &step, &[]).unwrap().stats
}

/// The QC map of the latent map's standard deviation holds what the tile statistics sum
/// (point-sampled: one entry per sampled core point), in cells of the tile's core, and both
/// routes see three passes 2 mm apart as σ = 2·√(2/3) mm.
#[test]
fn the_latent_std_map_holds_the_spread_of_the_passes_where_they_are() {
    let tile = TileKey { tx: 0, ty: 0 };
    let up = [0.0, 0.0, 1.0];
    let chunks = [
        strip_on(tile, 0, [0.0, 0.0], 1, |_, _| 0.0, up),
        strip_on(tile, 1, [0.033, 0.21], 1, |_, _| 0.002, up),
        strip_on(tile, 2, [0.017, 0.11], 1, |_, _| -0.002, up),
    ];
    let corrections = vec![TrajectoryCorrections::zeros(0, 8); chunks.len()];
    let expected = 0.002 * (2.0f64 / 3.0).sqrt();
    for (grid, sampled) in [(0.01, true), (0.05, false)] {
        let params = Parameters { point_latent_below_grid_m: 0.02, ..Default::default() };
        let step = IterationStep::new(grid, 0.05);
        let gather = LatentGather { std_map: true, map: true };
        let mut e =
            estimate_tile_recording(tile, &chunks, &corrections, &params, &step, &[], None, None, gather).unwrap();
        let map = e.latent_std.take().expect("asked for the σ map");
        let latent = e.latent_map.take().expect("asked for the latent map");
        // Recording the maps changes nothing else.
        assert_eq!(e, estimate_tile(tile, &chunks, &corrections, &params, &step, &[]).unwrap());
        // The exported map: every observation in one voxel point, on the passes' mean
        // surface (z = 0 where all three overlap, ±1 mm where two do), facing up.
        let observations: u64 = latent.iter().map(|p| p.observations as u64).sum();
        assert_eq!(observations, e.stats.points_used, "sampled {sampled}");
        assert!(latent.len() > 100, "{} map points", latent.len());
        let mut heights: Vec<f64> = latent.iter().map(|p| p.position[2].abs()).collect();
        heights.sort_by(f64::total_cmp);
        assert!(heights[heights.len() / 2] < 2e-4, "median |z| {} (sampled {sampled})", heights[heights.len() / 2]);
        assert!(heights[heights.len() - 1] < 1.05e-3, "largest |z| {}", heights[heights.len() - 1]);
        for p in &latent {
            assert!(p.normal[2] > 0.999 && (2.0..8.2).contains(&p.position[0]), "{p:?}");
            assert!(p.passes >= 2 && p.std_m < 0.0021, "{p:?}");
        }
        assert_eq!(map.side, 15);
        let count: u64 = map.count.iter().map(|&c| c as u64).sum();
        let sum: f64 = map.std_sum_m.iter().sum();
        if sampled {
            assert_eq!(count, e.stats.pixels_shared);
            assert!((sum - e.stats.pixel_std_sum_m).abs() < 1e-9 * sum.max(1.0), "{sum} {}", e.stats.pixel_std_sum_m);
        }
        assert!(count > 100, "{count} points mapped");
        // Every observed cell lies under the strips (x in [2, 6.1] m, y in [2, 7.8] m) and
        // holds about the three passes' spread.
        for j in 0..map.side {
            for i in 0..map.side {
                if let Some(mean) = map.mean_m(i, j) {
                    let (x, y) = (i as f64 + 0.5, j as f64 + 0.5);
                    assert!((2.0..7.0).contains(&x) && (2.0..8.0).contains(&y), "cell ({i}, {j})");
                    assert!((mean - expected).abs() < 0.35 * expected, "cell ({i}, {j}) {mean} (sampled {sampled})");
                }
            }
        }
    }
}

/// A car that one of three passes saw on a road (4.5 cm high, in the road's segment and
/// model) must not spoil the latent height of the two passes that agree: without the
/// agreement gate their points under it read a third of its height and are rejected as
/// outliers; with it they are observations with residual zero.
#[test]
fn covering_triangles_far_from_the_consensus_are_left_out() {
    let tile = TileKey { tx: 0, ty: 0 };
    let up = [0.0, 0.0, 1.0];
    let on_car = |x: f64, y: f64| (3.0..4.0).contains(&x) && (4.0..5.5).contains(&y);
    let chunks = [
        strip_on(tile, 0, [0.0, 0.0], 1, |_, _| 0.0, up),
        strip_on(tile, 1, [0.033, 0.21], 1, |_, _| 0.0, up),
        strip_on(tile, 2, [0.017, 0.11], 1, |x, y| if on_car(x, y) { 0.045 } else { 0.0 }, up),
    ];
    let (gated, all) = (fine_pass_stats(tile, &chunks, 0.012, 2.0), fine_pass_stats(tile, &chunks, 0.012, 0.0));
    // Points of passes 0 and 1 on the car's footprint, away from its edges.
    let under_car = chunks[..2]
        .iter()
        .flat_map(|c| (0..c.len()).map(move |k| (c.t0[k][0] + c.r[k][0], c.t0[k][1] + c.r[k][1])))
        .filter(|&(x, y)| (3.1..3.9).contains(&(x as f64)) && (4.1..5.4).contains(&(y as f64)))
        .count() as u64;
    assert!(under_car > 20, "{under_car}");
    assert!(gated.points_used >= all.points_used + under_car, "{} {} {under_car}", gated.points_used, all.points_used);
    let rms = |s: &TileStats| (s.residual_sum2_m2 / s.points_used as f64).sqrt();
    assert!(rms(&gated) < rms(&all), "{} {}", rms(&gated), rms(&all));
}

/// Two passes 7 cm above two others (more than the gate's 6 cm): judged against the
/// consensus of all four, every triangle stays, so the gate changes nothing and the offset
/// passes remain outliers of the rest. A gate judged against the point alone would let each
/// pair agree with itself and split the map into two layers.
#[test]
fn passes_off_together_are_not_split_into_layers() {
    let tile = TileKey { tx: 0, ty: 0 };
    let up = [0.0, 0.0, 1.0];
    let chunks = [
        strip_on(tile, 0, [0.0, 0.0], 1, |_, _| 0.0, up),
        strip_on(tile, 1, [0.033, 0.21], 1, |_, _| 0.0, up),
        strip_on(tile, 2, [0.017, 0.11], 1, |_, _| 0.07, up),
        strip_on(tile, 3, [0.051, 0.33], 1, |_, _| 0.07, up),
    ];
    let (gated, all) = (fine_pass_stats(tile, &chunks, 0.03, 2.0), fine_pass_stats(tile, &chunks, 0.03, 0.0));
    assert_eq!(gated, all);
    assert!(gated.points_modelled > 1000 && gated.points_used < gated.points_modelled / 10, "{gated:?}");
}

/// On a plane, the exact point-sampled latent surface, the one sampled at pixel centres and
/// a fine raster give the same residuals: two strips 4 mm apart meet in the middle
/// (residuals ±2 mm), and the blocks agree.
#[test]
fn point_sampled_latent_matches_fine_raster() {
    let tile = TileKey { tx: 0, ty: 0 };
    let chunks = [plane_strip(tile, 0, 0.0, [0.0, 0.0]), plane_strip(tile, 1, 0.004, [0.033, 0.21])];
    let corrections = vec![TrajectoryCorrections::zeros(0, 8); 2];
    let step = IterationStep::new(0.01, 0.05);
    // All with the map held: the comparison is of the latent surfaces, and the consistent
    // gradient (point-sampled steps only) spreads a point's pull over the covering passes.
    let run = |below: f64, share: f64| {
        let params = Parameters {
            point_latent_below_grid_m: below,
            latent_pixel_share: share,
            consistent_gradient: false,
            ..Default::default()
        };
        estimate_tile(tile, &chunks, &corrections, &params, &step, &[]).unwrap()
    };
    let (raster, exact, by_pixel) = (run(0.0, 0.0), run(0.02, 0.0), run(0.02, 0.7));
    for e in [&raster, &exact, &by_pixel] {
        assert!(e.stats.points_used > 500, "{:?}", e.stats.points_used);
        let mean = e.stats.residual_sum_m / e.stats.points_used as f64;
        let rms = (e.stats.residual_sum2_m2 / e.stats.points_used as f64).sqrt();
        assert!(mean.abs() < 2e-4 && (rms - 0.002).abs() < 2e-4, "mean {mean}, rms {rms}");
    }
    // Points near the overlap's edge need all four pixels in the raster, but only coverage
    // when sampled exactly or at the pixel holding them.
    assert!(exact.stats.points_used >= raster.stats.points_used);
    assert!(by_pixel.stats.points_used >= raster.stats.points_used);
    // The vertical pull per observation agrees.
    for other in [&exact, &by_pixel] {
        for (a, b) in raster.blocks.iter().zip(&other.blocks) {
            let pull = |t: &TrajectoryBlocks| {
                t.blocks.iter().map(|b| b.rhs[2]).sum::<f64>()
                    / t.blocks.iter().map(|b| b.observations).sum::<u32>() as f64
            };
            let (ra, rb) = (pull(a), pull(b));
            assert!(ra.abs() > 1.0 && (ra - rb).abs() < 0.05 * ra.abs(), "{ra} vs {rb}");
        }
    }
}

/// Sampled at pixel centres, a point's own pass never counts as another: one pass alone
/// gives no observation, however its revolutions fall into the pixels; the same strip
/// coming back (more than 64 anchors later) is another pass, and the two meet in the middle.
/// On a tilted, slightly curved surface sampled by passes of different densities, the
/// latent heights agree with the exact route's to a fraction of a millimetre.
#[test]
fn pixel_sampled_latent_excludes_the_own_pass_and_matches_the_exact_route() {
    let tile = TileKey { tx: 0, ty: 0 };
    let alone = [plane_strip(tile, 0, 0.0, [0.0, 0.0])];
    let stats = fine_pass_stats_on(tile, &alone, 0.05, 0.0, 0.7);
    assert!(stats.points_modelled == 0 && stats.points_used == 0, "{stats:?}");
    // The strip again 200 anchors later, 4 mm higher: another pass of the same strip.
    let mut back = plane_strip(tile, 0, 0.004, [0.033, 0.21]);
    back.anchor.iter_mut().for_each(|a| *a += 200);
    let mut both = alone[0].clone();
    let offset = both.len() as u32;
    both.t0.extend_from_slice(&back.t0);
    both.r.extend_from_slice(&back.r);
    both.normal.extend_from_slice(&back.normal);
    both.anchor.extend_from_slice(&back.anchor);
    both.lambda.extend_from_slice(&back.lambda);
    let link = |v: &u32| if *v == NO_NEIGHBOUR { NO_NEIGHBOUR } else { v + offset };
    both.right.extend(back.right.iter().map(link));
    both.down.extend(back.down.iter().map(link));
    both.edge_limit.extend_from_slice(&back.edge_limit);
    both.segment.extend(back.segment.iter().map(|s| s + 1));
    both.source.extend(back.source.iter().map(|s| s + offset));
    let stats = fine_pass_stats_on(tile, &[both], 0.05, 0.0, 0.7);
    let rms = (stats.residual_sum2_m2 / stats.points_used as f64).sqrt();
    assert!(stats.points_used > 500 && (rms - 0.002).abs() < 1e-4, "{} used, rms {rms}", stats.points_used);

    // Three passes over a gently curved, tilted surface, one of them twice as dense.
    let height = |x: f64, y: f64| 0.05 * x - 0.03 * y + 0.02 * (x - 4.0) * (x - 4.0);
    let n = normalize([-0.05, 0.03, 1.0]);
    let chunks = [
        strip_on(tile, 0, [0.0, 0.0], 1, height, n),
        strip_on(tile, 1, [0.033, 0.21], 2, |x, y| height(x, y) + 0.003, n),
        strip_on(tile, 2, [0.071, 0.37], 1, |x, y| height(x, y) - 0.002, n),
    ];
    let (exact, by_pixel) =
        (fine_pass_stats_on(tile, &chunks, 0.05, 0.0, 0.0), fine_pass_stats_on(tile, &chunks, 0.05, 0.0, 0.7));
    let mean = |s: &TileStats| s.residual_sum_m / s.points_used as f64;
    let rms = |s: &TileStats| (s.residual_sum2_m2 / s.points_used as f64).sqrt();
    assert!(by_pixel.points_used as f64 >= 0.97 * exact.points_used as f64, "{by_pixel:?} {exact:?}");
    assert!((mean(&by_pixel) - mean(&exact)).abs() < 1e-4, "{} {}", mean(&by_pixel), mean(&exact));
    assert!((rms(&by_pixel) - rms(&exact)).abs() < 2e-4, "{} {}", rms(&by_pixel), rms(&exact));
}

/// With a consistent gradient, a trajectory's blocks carry the gradient of the cost the
/// common-mode field minimises, `½ ω Σ e²` over the used points with the latent map moving
/// along: checked against a central difference on three passes over a plane, one of them
/// twice as dense and 4 mm off. Holding the map fixed gives another gradient there (the
/// passes' fixed points differ), which is what made the two levels fight.
#[test]
fn consistent_gradient_is_the_gradient_of_the_reduced_cost() {
    let tile = TileKey { tx: 0, ty: 0 };
    // Half a metre up, so that no shift moves a point across a 1 m cell boundary.
    let chunks = [
        plane_strip(tile, 0, 0.5, [0.0, 0.0]),
        plane_strip_every(tile, 1, 0.504, [0.033, 0.21], 2),
        plane_strip(tile, 2, 0.5, [0.071, 0.37]),
    ];
    let step = IterationStep::new(0.01, 0.05);
    // Both routes: exact sampling at the points, and at pixel centres.
    for share in [0.0, 0.7] {
        let run = |consistent: bool, trajectory: usize, dz: f64| {
            let params = Parameters {
                point_latent_below_grid_m: 0.02,
                consistent_gradient: consistent,
                latent_pixel_share: share,
                ..Default::default()
            };
            let mut corrections = vec![TrajectoryCorrections::zeros(0, 8); 3];
            corrections[trajectory].values.iter_mut().for_each(|c| c[2] = dz);
            estimate_tile(tile, &chunks, &corrections, &params, &step, &[]).unwrap()
        };
        let weight = 1.0 / Parameters::default().sigma_distance_m.powi(2);
        let cost = |e: &TileEstimate| 0.5 * weight * e.stats.residual_sum2_m2;
        let h = 1e-6;
        let (mut common_consistent, mut common_fixed_map) = (0.0, 0.0);
        for trajectory in 0..3 {
            let numeric = (cost(&run(true, trajectory, h)) - cost(&run(true, trajectory, -h))) / (2.0 * h);
            let pull = |consistent: bool| -> f64 {
                let e = run(consistent, trajectory, 0.0);
                e.blocks
                    .iter()
                    .filter(|t| t.trajectory == trajectory as u32)
                    .flat_map(|t| &t.blocks)
                    .map(|b| b.rhs[2])
                    .sum()
            };
            // The blocks' right-hand side is the negative gradient (`H δ = rhs`).
            let (consistent, fixed_map) = (-pull(true), -pull(false));
            assert!(numeric.abs() > 1.0, "trajectory {trajectory}: {numeric}");
            assert!(
                (consistent - numeric).abs() < 0.01 * numeric.abs(),
                "trajectory {trajectory}: {consistent} vs {numeric}"
            );
            eprintln!("trajectory {trajectory}: reduced-cost gradient {numeric:.3}, consistent {consistent:.3}, map held {fixed_map:.3}");
            if trajectory == 0 {
                // The sparse pass: the map-fixed pull misses what the dense pass's points pull.
                assert!((fixed_map - numeric).abs() > 0.1 * numeric.abs(), "{fixed_map} vs {numeric}");
            }
            common_consistent += consistent;
            common_fixed_map += fixed_map;
        }
        // Moving every pass together changes no residual, so the reduced cost has no gradient
        // along it; holding the map fixed invents one, which only the prior would balance.
        assert!(common_consistent.abs() < 1e-6 * 1000.0, "share {share}: {common_consistent}");
        assert!(common_fixed_map.abs() > 100.0, "share {share}: {common_fixed_map}");
    }
}

/// Deterministic uniform numbers in [0, 1) (a linear congruential generator).
fn uniform(seed: &mut u64) -> f64 {
    *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    (*seed >> 11) as f64 / (1u64 << 53) as f64
}

/// The branch-free accumulation changes no result: a masked-off candidate leaves a sample
/// bit for bit as it was, and the taken ones add up exactly as plain sums do.
#[test]
fn masked_sample_adds_exactly_the_taken_candidates() {
    let mut seed = 5u64;
    let mut rand = || uniform(&mut seed);
    let mut masked = Sample::default();
    let (mut sum, mut sum2, mut slope, mut vehicle, mut count) = (0.0, 0.0, [0.0; 2], [0.0; 2], 0u32);
    for _ in 0..5000 {
        let (h, hx, hy) = (rand() - 0.5, rand() - 0.5, rand() - 0.5);
        let v = [549_800.0 + rand() * 100.0, 5_803_400.0 + rand() * 100.0];
        let take = rand() < 0.4;
        masked.add_masked(take, h, hx, hy, v);
        if take {
            sum += h;
            sum2 += h * h;
            slope[0] += hx;
            slope[1] += hy;
            vehicle[0] += v[0];
            vehicle[1] += v[1];
            count += 1;
        }
        let got = [masked.sum, masked.sum2, masked.slope[0], masked.slope[1], masked.vehicle[0], masked.vehicle[1]];
        let want = [sum, sum2, slope[0], slope[1], vehicle[0], vehicle[1]];
        assert_eq!(got.map(f64::to_bits), want.map(f64::to_bits));
        assert_eq!(masked.count, count);
    }
    assert!(count > 1500 && count < 2500);
}

/// The pulls on triangles lying on another model than their corner's reach exactly their
/// corners, each once, when the points are taken in order (the cursor over the sorted
/// entries); the pull through the corner's own model is returned (to join the point's own
/// observation), and entries without weight add nothing.
#[test]
fn corner_pulls_of_other_models_reach_their_corners() {
    let mut models = vec![SurfaceModel::new(); 3];
    for (m, w) in models.iter_mut().zip([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.6, 0.8]]) {
        m.w = w;
    }
    let n = 7;
    let measurement: Vec<[f64; 3]> = (0..n).map(|i| [i as f64, 1.0, -2.0]).collect();
    let mut sums = vec![[0.0; 2]; n];
    sums[2] = [0.5, 0.01];
    let other_models =
        vec![(1, 1, [2.0, 0.5]), (1, 2, [1.0, -0.25]), (3, 2, [0.0, 0.0]), (4, 1, [3.0, 1.5]), (6, 2, [0.2, 0.1])];
    let mut pulls = CornerPulls { sums: sums.clone(), other_models: other_models.clone(), next_other: 0 };
    let mut reached = 0;
    for a in 0..n {
        let (mut got, mut apart) = (IntervalMoments::default(), IntervalMoments::default());
        let own = pulls.take(a, &models, &measurement, &mut got, Some(&mut apart), 0.25);
        assert_eq!(own, (a == 2).then_some(sums[2]), "point {a}");
        let mut want = IntervalMoments::default();
        let entries = other_models.iter().filter(|o| o.0 == a && o.2[0] > 0.0);
        for &(_, model, [w_sum, we_sum]) in entries {
            let w = models[model as usize].w;
            let rw = cross(measurement[a], w);
            want.add(&[w[0], w[1], w[2], rw[0], rw[1], rw[2]], -we_sum / w_sum, w_sum, 0.25);
            reached += 1;
        }
        assert_eq!(format!("{got:?}"), format!("{want:?}"), "point {a}");
        // The same pulls summed apart, for the calibration's terms to leave out.
        assert_eq!(format!("{apart:?}"), format!("{want:?}"), "point {a}");
    }
    assert_eq!(reached, 4);
}

#[test]
fn floor_i64_matches_floor() {
    for x in [-2.5, -2.0, -1e-12, -0.0, 0.0, 1e-12, 0.5, 1.0, 3.999_999, 1e15 + 0.5, -1e15 - 0.5] {
        assert_eq!(floor_i64(x), x.floor() as i64, "{x}");
    }
}

/// A triangle's centre box holds exactly the pixel centres a per-pixel barycentric test
/// accepts (those inside flagged so), with the barycentric heights, and indexes them in
/// the tile's pixels.
#[test]
fn centre_box_matches_barycentric_reference() {
    let mut seed = 11u64;
    let mut rand = |scale: f64| uniform(&mut seed) * scale;
    let grid = PixelGrid { u0: 3.2, v0: -1.7, size: 0.05, inv: 1.0 / 0.05, nu: 16, nv: 14, offset: 1000 };
    let (nu, nv) = (grid.nu as i64, grid.nv as i64);
    // Pixel coordinates (centre (i, j) at (i, j)) to the plane's metres.
    let metres = |x: f64, y: f64| [grid.u0 + (x + 0.5) * grid.size, grid.v0 + (y + 0.5) * grid.size];
    for _ in 0..2000 {
        let x = [rand(20.0) - 2.0, rand(20.0) - 2.0, rand(20.0) - 2.0];
        let y = [rand(20.0) - 2.0, rand(20.0) - 2.0, rand(20.0) - 2.0];
        let h = [rand(1.0), rand(1.0), rand(1.0)];
        let corner = |k: usize| {
            let [u, v] = metres(x[k], y[k]);
            [u, v, h[k]]
        };
        // By the per-centre test and by scanline spans.
        let (mut got, mut spans) = (std::collections::BTreeMap::new(), std::collections::BTreeMap::new());
        let pixel = |at: usize| ((at - grid.offset) % nu as usize, (at - grid.offset) / nu as usize);
        if let Some(plane) = PlaneTriangle::new([corner(0), corner(1), corner(2)]) {
            if let Some(centres) = grid.centres_under(&plane) {
                let mut visited = 0;
                centres.for_each(|at, v, inside| {
                    visited += 1;
                    if inside {
                        assert!(got.insert(pixel(at), v).is_none(), "pixel visited twice");
                    }
                });
                assert_eq!(visited, centres.len());
                centres.for_each_inside(|at, v| {
                    assert!(spans.insert(pixel(at), v).is_none(), "pixel visited twice in a span");
                });
            }
        }
        let area = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0]);
        if area.abs() < 1e-6 {
            continue;
        }
        for j in 0..nv {
            for i in 0..nu {
                let (px, py) = (i as f64, j as f64);
                let wa = ((x[1] - px) * (y[2] - py) - (x[2] - px) * (y[1] - py)) / area;
                let wb = ((x[2] - px) * (y[0] - py) - (x[0] - px) * (y[2] - py)) / area;
                let wc = 1.0 - wa - wb;
                let margin = wa.min(wb).min(wc);
                // Pixels right on an edge may go either way.
                if margin.abs() < 1e-6 {
                    continue;
                }
                let inside = margin > 0.0;
                for found in [&got, &spans] {
                    assert_eq!(found.contains_key(&(i as usize, j as usize)), inside, "pixel {i},{j}");
                    if inside {
                        let expect = wa * h[0] + wb * h[1] + wc * h[2];
                        assert!((found[&(i as usize, j as usize)] - expect).abs() < 1e-9, "pixel {i},{j}");
                    }
                }
            }
        }
    }
}
