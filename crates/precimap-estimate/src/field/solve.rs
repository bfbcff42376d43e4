//! The field's solve: the tiles' data equations and every anchor's prior, smoothness and
//! curvature terms in one sparse system ([`solve_field`]), with the campaign's rotation through
//! its Schur complement; and [`remove_field_share`] for the step momentum carries on.

use super::{accumulate, bilinear, CampaignMotion, FieldEquations, FieldNode, FieldSolution, FieldTrajectory};
use precimap_core::corrections::TrajectoryCorrections;
use precimap_core::geom::{skew, Mat3, Vec3};
use precimap_core::Parameters;
use precimap_solve::sparse::{SparseError, SymmetricSparse};
use std::collections::BTreeMap;

/// The motion's part of the field's normal equations: its coupling to every field unknown
/// (`∂²/∂field ∂ω`, three columns), its own block and right-hand side.
pub(super) struct MotionTerms {
    origin: [f64; 3],
    coupling: Vec<[f64; 3]>,
    own: Mat3,
    rhs: Vec3,
}

impl MotionTerms {
    /// A translation term: residual `Σ row·field + ω × d + value` of weight `w` per axis.
    fn add(&mut self, row: &[(usize, f64)], per_node: usize, d: [f64; 3], value: [f64; 3], w: [f64; 3]) {
        // `∂(ω × d)/∂ω = −[d]×`.
        let m = -skew(&Vec3::from(d));
        for &(node, phi) in row {
            for c in 0..3 {
                for j in 0..3 {
                    self.coupling[per_node * node + c][j] += w[c] * phi * m[(c, j)];
                }
            }
        }
        let weighted = Mat3::from_fn(|j, c| w[c] * m[(c, j)]);
        self.own += weighted * m;
        self.rhs -= weighted * Vec3::from(value);
    }
}

/// Rotation unknowns per node of the field the parameters ask for: none, the heading (1), or
/// heading and tilt (3).
pub fn rotation_axes(params: &Parameters) -> usize {
    match (params.common_mode_heading, params.common_mode_tilt) {
        (false, _) => 0,
        (true, false) => 1,
        (true, true) => 3,
    }
}

/// Numbers, in grid order, the nodes of `seed` and every node an anchor of `trajectories`
/// touches.
pub(super) fn number_nodes(
    seed: impl IntoIterator<Item = FieldNode>,
    trajectories: &[FieldTrajectory],
    spacing: f64,
) -> BTreeMap<FieldNode, usize> {
    let mut index: BTreeMap<FieldNode, usize> = seed.into_iter().map(|n| (n, 0)).collect();
    for tr in trajectories {
        for p in tr.positions {
            for (n, phi) in bilinear(p[0], p[1], spacing) {
                if phi > 0.0 {
                    index.insert(n, 0);
                }
            }
        }
    }
    for (i, v) in index.values_mut().enumerate() {
        *v = i;
    }
    index
}

/// `previous` moved so that `current − previous` (the step momentum carries on) loses its
/// least-squares fit by a field on the same nodes: the field re-solves that part itself in the
/// next iteration, so carrying it as well overshoots and the two levels fight.
/// `trajectories` hold the current corrections and their anchors' positions; the field has
/// `rotation_axes` rotations per node as well ([`rotation_axes`]: 0, 1 for the heading, 3 with
/// the tilt).
pub fn remove_field_share(
    trajectories: &[FieldTrajectory],
    previous: &[TrajectoryCorrections],
    spacing: f64,
    rotation_axes: usize,
) -> Result<Vec<TrajectoryCorrections>, FieldError> {
    if previous.len() != trajectories.len() {
        return Err(FieldError::Trajectories { expected: trajectories.len(), found: previous.len() });
    }
    for (t, (tr, before)) in trajectories.iter().zip(previous).enumerate() {
        for anchors in [tr.corrections.values.len(), before.values.len()] {
            if anchors != tr.positions.len() {
                return Err(FieldError::Positions { trajectory: t, positions: tr.positions.len(), anchors });
            }
        }
    }
    let index = number_nodes(std::iter::empty(), trajectories, spacing);
    let nodes = index.len();
    // One scalar system for the three axes: Σ φφᵀ g = Σ φ d, with a small ridge for nodes that
    // anchors touch only at their far corner.
    let mut a = SymmetricSparse::new(nodes);
    // Per node the right-hand sides of x, y, z, the rotation about z (the heading), about x and
    // about y (the tilt).
    let mut b = vec![[0.0f64; 6]; nodes];
    for (tr, before) in trajectories.iter().zip(previous) {
        for ((p, now), was) in tr.positions.iter().zip(&tr.corrections.values).zip(&before.values) {
            let row: Vec<(usize, f64)> = bilinear(p[0], p[1], spacing)
                .iter()
                .filter(|(_, phi)| *phi > 0.0)
                .map(|(n, phi)| (index[n], *phi))
                .collect();
            for &(i, pi) in &row {
                for &(j, pj) in &row {
                    // Each unordered pair once (the row's nodes are distinct).
                    if i >= j {
                        a.add(i, j, pi * pj);
                    }
                }
                for c in 0..3 {
                    b[i][c] += pi * (now[c] - was[c]);
                }
                b[i][3] += pi * (now[5] - was[5]);
                b[i][4] += pi * (now[3] - was[3]);
                b[i][5] += pi * (now[4] - was[4]);
            }
        }
    }
    for i in 0..nodes {
        a.add(i, i, 1e-3);
    }
    let factor = a.factorise(MAX_FIELD_FACTOR_ENTRIES).map_err(|e| FieldError::from_sparse(e, nodes))?;
    let axes = 3 + rotation_axes;
    let per_axis: Vec<Vec<f64>> =
        (0..axes).map(|c| factor.solve(&b.iter().map(|v| v[c]).collect::<Vec<_>>())).collect();
    let fit = FieldSolution {
        spacing_m: spacing,
        nodes: index.keys().copied().collect(),
        values: (0..nodes).map(|i| [per_axis[0][i], per_axis[1][i], per_axis[2][i]]).collect(),
        observations: 0,
        motion: None,
        heading: if rotation_axes > 0 { per_axis[3].clone() } else { Vec::new() },
        tilt: if rotation_axes == 3 {
            (0..nodes).map(|i| [per_axis[4][i], per_axis[5][i]]).collect()
        } else {
            Vec::new()
        },
    };
    Ok(trajectories.iter().zip(previous).map(|(tr, before)| fit.apply(tr.positions, before)).collect())
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FieldError {
    #[error("trajectory {trajectory}: {positions} anchor positions for {anchors} anchors")]
    Positions { trajectory: usize, positions: usize, anchors: usize },
    #[error("{found} trajectories' previous corrections for {expected} trajectories")]
    Trajectories { expected: usize, found: usize },
    #[error("the common-mode field's normal equations are not positive definite ({nodes} nodes)")]
    Singular { nodes: usize },
    #[error(
        "the common-mode field's {nodes} nodes need {entries} factor entries, more than the {limit} \
         (8 bytes each) its solve may use; raise parameters.common_mode_field_m (the node spacing), \
         set parameters.common_mode_tilt to false (a third fewer unknowns) or \
         parameters.common_mode_heading to false (a quarter fewer), or set \
         parameters.common_mode_field_m to 0"
    )]
    TooLarge { nodes: usize, entries: usize, limit: usize },
    /// A system the field built wrongly (a bug, not the data's fault).
    #[error("the common-mode field's solve: {0}")]
    Solve(SparseError),
}

impl FieldError {
    fn from_sparse(e: SparseError, nodes: usize) -> Self {
        match e {
            SparseError::TooLarge { entries, limit } => FieldError::TooLarge { nodes, entries, limit },
            SparseError::NotPositiveDefinite { .. } => FieldError::Singular { nodes },
            e @ (SparseError::OutOfRange { .. } | SparseError::NotFinite { .. } | SparseError::Structure(_)) => {
                FieldError::Solve(e)
            }
        }
    }
}

/// Most factor entries the field's sparse solve may hold (8 bytes each: 1 GiB). A synthetic
/// street network of 248 km² at 15 m nodes needs 69 % of this with three unknowns per node, so
/// the limit lies near 350 km² of such a network; with the heading's fourth, 159 km² needs 71 %
/// and the limit lies near 215 km²; with the tilt's six, 89.3 km² need 86 % and the limit lies
/// near 100 km² (`precimap bench field-solve --blocks 150|120|90 --per-node 3|4|6`;
/// docs/design/estimation.md, "The common-mode field").
pub const MAX_FIELD_FACTOR_ENTRIES: usize = (1 << 30) / 8;

/// Solves the common-mode field from the tiles' data equations plus every anchor's prior,
/// smoothness and curvature terms, linearised about the current corrections.
pub fn solve_field<'a>(
    equations: impl IntoIterator<Item = &'a FieldEquations>,
    trajectories: &[FieldTrajectory],
    params: &Parameters,
) -> Result<FieldSolution, FieldError> {
    solve_field_within(equations, trajectories, params, MAX_FIELD_FACTOR_ENTRIES)
}

/// [`solve_field`] with at most `max_factor_entries` factor entries.
pub(super) fn solve_field_within<'a>(
    equations: impl IntoIterator<Item = &'a FieldEquations>,
    trajectories: &[FieldTrajectory],
    params: &Parameters,
    max_factor_entries: usize,
) -> Result<FieldSolution, FieldError> {
    let spacing = params.common_mode_field_m;
    for (t, tr) in trajectories.iter().enumerate() {
        if tr.positions.len() != tr.corrections.values.len() {
            return Err(FieldError::Positions {
                trajectory: t,
                positions: tr.positions.len(),
                anchors: tr.corrections.values.len(),
            });
        }
    }
    let equations: Vec<&FieldEquations> = equations.into_iter().collect();
    // Node numbering: every node a tile or an anchor touches.
    let index = number_nodes(equations.iter().flat_map(|e| e.nodes.iter().copied()), trajectories, spacing);
    let nodes = index.len();
    // Unknowns per node: the translation, then with the heading the rotation about z (index 3),
    // with the tilt the rotations about x and y (4 and 5).
    let axes = rotation_axes(params);
    let per_node = 3 + axes;
    let dim = per_node * nodes;
    let mut system = FieldSystem {
        h: SymmetricSparse::new(dim),
        rhs: vec![0.0f64; dim],
        per_node,
        rotation_unknowns: match axes {
            0 => &[],
            1 => &[(3, 2)],
            _ => &[(3, 2), (4, 0), (5, 1)],
        },
        motion: None,
    };
    let observations = system.add_data(&equations, &index, axes);
    // The campaign's rotation, solved with the field (`Parameters::campaign_motion`).
    system.motion = params.campaign_motion.then(|| MotionTerms::centred(trajectories, dim));
    let weights = AnchorWeights::new(params);
    system.add_anchor_terms(trajectories, &weights, &index, spacing);
    system.add_motion_prior(trajectories, &weights);
    system.add_field_prior(&weights);
    let (solution, motion) = system.solve(max_factor_entries, nodes)?;
    Ok(FieldSolution {
        spacing_m: spacing,
        nodes: index.keys().copied().collect(),
        values: (0..nodes).map(|i| std::array::from_fn(|c| solution[per_node * i + c])).collect(),
        observations,
        motion,
        heading: if axes > 0 { (0..nodes).map(|i| solution[per_node * i + 3]).collect() } else { Vec::new() },
        tilt: if axes == 3 {
            (0..nodes).map(|i| [solution[per_node * i + 4], solution[per_node * i + 5]]).collect()
        } else {
            Vec::new()
        },
    })
}

/// The weights of an anchor's prior, smoothness and curvature terms: prior and smoothness act on
/// each axis alike, one scalar weight per node pair.
struct AnchorWeights {
    prior: f64,
    smooth: f64,
    curvature: f64,
    prior_rotation: [f64; 3],
    smooth_rotation: f64,
    curvature_rotation: f64,
}

impl AnchorWeights {
    fn new(params: &Parameters) -> Self {
        let prior = 1.0 / (params.sigma_prior_position_m * params.sigma_prior_position_m);
        let smooth = 1.0 / (params.sigma_smooth_position_m * params.sigma_smooth_position_m);
        let curvature = match params.sigma_curvature_position_m {
            s if s > 0.0 => 1.0 / (s * s),
            _ => 0.0,
        };
        let rotation_weight = |sigma_deg: f64| match sigma_deg.to_radians() {
            s if s > 0.0 => 1.0 / (s * s),
            _ => 0.0,
        };
        Self {
            prior,
            smooth,
            curvature,
            prior_rotation: params.sigma_prior_rotation_axes_deg().map(rotation_weight),
            smooth_rotation: rotation_weight(params.sigma_smooth_rotation_deg),
            curvature_rotation: rotation_weight(params.sigma_curvature_rotation_deg),
        }
    }

    /// An anchor's own prior (translation, rotation weights), else the campaign's.
    fn anchor_prior(&self, tr: &FieldTrajectory, k: usize) -> ([f64; 3], [f64; 3]) {
        match tr.prior.and_then(|p| p.get(k)) {
            Some(w) => ([w[0], w[1], w[2]], [w[3], w[4], w[5]]),
            None => ([self.prior; 3], self.prior_rotation),
        }
    }
}

impl MotionTerms {
    /// Empty terms of a rotation about the centre of every anchor of `trajectories`, coupled to
    /// `dim` field unknowns.
    fn centred(trajectories: &[FieldTrajectory], dim: usize) -> Self {
        let count = trajectories.iter().map(|tr| tr.positions.len()).sum::<usize>().max(1);
        let sum: Vec3 = trajectories.iter().flat_map(|tr| tr.positions).map(|&p| Vec3::from(p)).sum();
        MotionTerms {
            origin: (sum / count as f64).into(),
            coupling: vec![[0.0; 3]; dim],
            own: Mat3::zeros(),
            rhs: Vec3::zeros(),
        }
    }
}

/// The field's normal equations while they are summed: `per_node` unknowns per node (the
/// translation, then the rotations), and the campaign's rotation bordering them.
struct FieldSystem {
    /// The lower triangle is what the factorisation reads: each block pair adds there once.
    h: SymmetricSparse,
    rhs: Vec<f64>,
    per_node: usize,
    /// The field's rotation unknowns: (index within the node, axis).
    rotation_unknowns: &'static [(usize, usize)],
    motion: Option<MotionTerms>,
}

impl FieldSystem {
    /// Adds the tiles' data equations (numbered by `index`; `axes` rotation unknowns per node);
    /// returns their observations.
    fn add_data(&mut self, equations: &[&FieldEquations], index: &BTreeMap<FieldNode, usize>, axes: usize) -> u64 {
        let (h, rhs, per_node) = (&mut self.h, &mut self.rhs, self.per_node);
        let mut observations = 0;
        for e in equations {
            observations += e.observations;
            let global: Vec<usize> = e.nodes.iter().map(|n| index[n]).collect();
            // Equations summed without the heading (an older field object) leave its data out.
            let heading = axes > 0 && e.heading_pairs.len() == e.pairs.len() && e.heading_rhs.len() == e.nodes.len();
            let tilt = heading && axes == 3 && e.tilt_pairs.len() == e.pairs.len() && e.tilt_rhs.len() == e.nodes.len();
            for (k, &(a, b, m)) in e.pairs.iter().enumerate() {
                let (ga, gb) = (per_node * global[a as usize], per_node * global[b as usize]);
                for r in 0..3 {
                    for c in 0..3 {
                        // A node's own block is symmetric: its lower half once.
                        if ga != gb || r >= c {
                            h.add(ga + r, gb + c, m[3 * r + c]);
                        }
                    }
                }
                if heading {
                    let x = &e.heading_pairs[k];
                    for c in 0..3 {
                        h.add(ga + c, gb + 3, x[c]);
                        if ga != gb {
                            h.add(ga + 3, gb + c, x[3 + c]);
                        }
                    }
                    h.add(ga + 3, gb + 3, x[6]);
                }
                if tilt {
                    // As `FieldEquations::tilt_pairs` lays them out; a node's own block adds each of
                    // its entries once.
                    let y = &e.tilt_pairs[k];
                    for j in 0..2 {
                        for c in 0..3 {
                            h.add(ga + c, gb + 4 + j, y[c * 2 + j]);
                            if ga != gb {
                                h.add(ga + 4 + j, gb + c, y[6 + j * 3 + c]);
                            }
                        }
                        h.add(ga + 3, gb + 4 + j, y[12 + j]);
                        if ga != gb {
                            h.add(ga + 4 + j, gb + 3, y[14 + j]);
                        }
                        for l in 0..2 {
                            if ga != gb || j >= l {
                                h.add(ga + 4 + j, gb + 4 + l, y[16 + 2 * j + l]);
                            }
                        }
                    }
                }
            }
            if heading {
                for (n, r) in e.heading_rhs.iter().enumerate() {
                    rhs[per_node * global[n] + 3] += r;
                }
            }
            if tilt {
                for (n, r) in e.tilt_rhs.iter().enumerate() {
                    rhs[per_node * global[n] + 4] += r[0];
                    rhs[per_node * global[n] + 5] += r[1];
                }
            }
            for (n, r) in e.rhs.iter().enumerate() {
                for c in 0..3 {
                    rhs[per_node * global[n] + c] += r[c];
                }
            }
        }
        observations
    }

    /// One term of an anchor's prior, smoothness or curvature on `value` (a correction, or a
    /// difference of them): on the translation, residual `Σ row·field + ω × d + value[..3]` of
    /// weight `weight`; with the field's rotation, also on each of its axes, residual
    /// `Σ row·ρ + value[3..]` of weight `rotation_weight` (plus the campaign's rotation where
    /// `sees_motion`: only the prior sees it, a constant drops out of differences).
    fn add_term(
        &mut self,
        row: &[(usize, f64)],
        d: [f64; 3],
        value: [f64; 6],
        weight: [f64; 3],
        rotation_weight: [f64; 3],
        sees_motion: bool,
    ) {
        let (h, rhs, per_node) = (&mut self.h, &mut self.rhs, self.per_node);
        for &(a, ra) in row {
            for c in 0..3 {
                rhs[per_node * a + c] -= weight[c] * ra * value[c];
            }
            for &(b, rb) in row {
                // Each unordered pair of nodes once.
                if a >= b {
                    for c in 0..3 {
                        h.add(per_node * a + c, per_node * b + c, weight[c] * ra * rb);
                    }
                }
            }
        }
        if let Some(m) = self.motion.as_mut() {
            m.add(row, per_node, d, [value[0], value[1], value[2]], weight);
        }
        for &(unknown, axis) in self.rotation_unknowns {
            let weight = rotation_weight[axis];
            for &(a, ra) in row {
                rhs[per_node * a + unknown] -= weight * ra * value[3 + axis];
                for &(b, rb) in row {
                    if a >= b {
                        h.add(per_node * a + unknown, per_node * b + unknown, weight * ra * rb);
                    }
                }
                if let (true, Some(m)) = (sees_motion, self.motion.as_mut()) {
                    m.coupling[per_node * a + unknown][axis] += weight * ra;
                }
            }
        }
    }

    /// Adds every anchor's prior, its smoothness with the next anchor and its curvature with
    /// both neighbours (numbered by `index`, nodes `spacing` apart).
    fn add_anchor_terms(
        &mut self,
        trajectories: &[FieldTrajectory],
        weights: &AnchorWeights,
        index: &BTreeMap<FieldNode, usize>,
        spacing: f64,
    ) {
        let origin = self.motion.as_ref().map_or([0.0; 3], |m| m.origin);
        let AnchorWeights { smooth, curvature, smooth_rotation, curvature_rotation, .. } = *weights;
        let row_at = |p: &[f64; 3]| -> Vec<(usize, f64)> {
            bilinear(p[0], p[1], spacing)
                .iter()
                .filter(|(_, phi)| *phi > 0.0)
                .map(|(n, phi)| (index[n], *phi))
                .collect()
        };
        for tr in trajectories {
            // The trajectory's own curvature σ's where it has them (the term is on for all or none).
            let (curvature, curvature_rotation) = match tr.curvature.map(crate::CurvatureModel::weights) {
                Some(w) if curvature > 0.0 => ([w[0], w[1], w[2]], [w[3], w[4], w[5]]),
                _ => ([curvature; 3], [curvature_rotation; 3]),
            };
            let values = &tr.corrections.values;
            let rows: Vec<Vec<(usize, f64)>> = tr.positions.iter().map(row_at).collect();
            let d: Vec<[f64; 3]> = tr.positions.iter().map(|p| std::array::from_fn(|a| p[a] - origin[a])).collect();
            for (k, row) in rows.iter().enumerate() {
                let (prior, prior_rotation) = weights.anchor_prior(tr, k);
                self.add_term(row, d[k], values[k], prior, prior_rotation, true);
                if k + 1 < rows.len() {
                    let mut diff = rows[k + 1].clone();
                    for &(a, ra) in row {
                        accumulate(&mut diff, a, -ra);
                    }
                    let dv: [f64; 6] = std::array::from_fn(|c| values[k + 1][c] - values[k][c]);
                    let dd = std::array::from_fn(|a| d[k + 1][a] - d[k][a]);
                    self.add_term(&diff, dd, dv, [smooth; 3], [smooth_rotation; 3], false);
                }
                if curvature[0] > 0.0 && k >= 1 && k + 1 < rows.len() {
                    let mut second: Vec<(usize, f64)> = Vec::with_capacity(12);
                    for (r, f) in [(&rows[k - 1], 1.0), (row, -2.0), (&rows[k + 1], 1.0)] {
                        for &(a, ra) in r {
                            accumulate(&mut second, a, f * ra);
                        }
                    }
                    let dv: [f64; 6] =
                        std::array::from_fn(|c| values[k - 1][c] - 2.0 * values[k][c] + values[k + 1][c]);
                    let dd = std::array::from_fn(|c| d[k - 1][c] - 2.0 * d[k][c] + d[k + 1][c]);
                    self.add_term(&second, dd, dv, curvature, curvature_rotation, false);
                }
            }
        }
    }

    /// The rotation prior sees the motion's rotation directly: it holds the campaign's mean
    /// attitude correction.
    fn add_motion_prior(&mut self, trajectories: &[FieldTrajectory], weights: &AnchorWeights) {
        if let Some(m) = self.motion.as_mut() {
            for tr in trajectories {
                for (k, v) in tr.corrections.values.iter().enumerate() {
                    let prior_rotation = weights.anchor_prior(tr, k).1;
                    for i in 0..3 {
                        m.own[(i, i)] += prior_rotation[i];
                        m.rhs[i] -= prior_rotation[i] * v[3 + i];
                    }
                }
            }
        }
    }

    /// A node that only a scan head's lever arm reaches (no anchor near it) may see data in some
    /// directions only; a weak prior on the field itself (σ 10 × the anchors') keeps it definite.
    fn add_field_prior(&mut self, weights: &AnchorWeights) {
        let (prior, prior_rotation) = (weights.prior, weights.prior_rotation);
        for i in 0..self.rhs.len() {
            let own_prior = match i % self.per_node {
                3 => prior_rotation[2],
                4 => prior_rotation[0],
                5 => prior_rotation[1],
                _ => prior,
            };
            self.h.add(i, i, own_prior * 1e-2);
        }
    }

    /// Factorises the system (at most `max_factor_entries` entries; `nodes` for the errors) and
    /// solves it: the field's unknowns and, when the system holds it, the campaign's rotation.
    fn solve(self, max_factor_entries: usize, nodes: usize) -> Result<(Vec<f64>, Option<CampaignMotion>), FieldError> {
        let factor = self.h.factorise(max_factor_entries).map_err(|e| FieldError::from_sparse(e, nodes))?;
        let mut solution = factor.solve(&self.rhs);
        // The rotation by the Schur complement of the field's block: the field's factor solves the
        // three coupling columns, then the 3×3 system gives the rotation and the field follows.
        let motion = match self.motion {
            Some(m) => {
                let columns: Vec<Vec<f64>> =
                    (0..3).map(|j| factor.solve(&m.coupling.iter().map(|c| c[j]).collect::<Vec<_>>())).collect();
                let mut schur = m.own;
                let mut reduced = m.rhs;
                for i in 0..3 {
                    for (k, c) in m.coupling.iter().enumerate() {
                        reduced[i] -= c[i] * solution[k];
                        for j in 0..3 {
                            schur[(i, j)] -= c[i] * columns[j][k];
                        }
                    }
                }
                let rotation = schur.cholesky().ok_or(FieldError::Singular { nodes })?.solve(&reduced);
                for (k, x) in solution.iter_mut().enumerate() {
                    *x -= (0..3).map(|j| columns[j][k] * rotation[j]).sum::<f64>();
                }
                Some(CampaignMotion { origin: m.origin, rotation: [rotation[0], rotation[1], rotation[2]] })
            }
            None => None,
        };
        Ok((solution, motion))
    }
}
