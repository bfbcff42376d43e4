//! Exact solve of a sparse symmetric positive definite system: reverse Cuthill–McKee ordering,
//! then a Cholesky factorisation in the envelope (skyline) of the reordered matrix, which holds
//! all of the factor's fill-in.
//!
//! Written for the common-mode field (`precimap_estimate::field`): its unknowns are the nodes of a
//! grid laid over the streets, coupled only to the nodes near them, so after RCM each row reaches
//! back only across the width of the street network. Memory and time then grow with the envelope
//! (Σ row widths, Σ width²), not with the square and cube of the unknowns as a dense solve does.

use std::collections::{HashMap, VecDeque};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SparseError {
    #[error("the system is not positive definite: pivot {pivot} of {unknowns} is {value:e}")]
    NotPositiveDefinite { pivot: usize, unknowns: usize, value: f64 },
    #[error("the system's envelope holds {entries} entries after ordering, more than the {limit} it may use")]
    TooLarge { entries: usize, limit: usize },
    #[error("entry ({row}, {column}) lies outside the {unknowns} unknowns")]
    OutOfRange { row: usize, column: usize, unknowns: usize },
}

/// A symmetric matrix by its lower triangle, accumulated entry by entry.
#[derive(Clone, Debug, Default)]
pub struct SymmetricSparse {
    unknowns: usize,
    /// `(row, column)` with `row ≥ column` → value.
    lower: HashMap<(u32, u32), f64>,
    out_of_range: Option<(usize, usize)>,
}

impl SymmetricSparse {
    pub fn new(unknowns: usize) -> Self {
        Self { unknowns, lower: HashMap::new(), out_of_range: None }
    }

    pub fn unknowns(&self) -> usize {
        self.unknowns
    }

    /// Adds `value` to entry (i, j) and, by symmetry, to (j, i): call it once per unordered pair.
    #[inline]
    pub fn add(&mut self, i: usize, j: usize, value: f64) {
        if i >= self.unknowns || j >= self.unknowns {
            self.out_of_range.get_or_insert((i, j));
            return;
        }
        let key = if i >= j { (i as u32, j as u32) } else { (j as u32, i as u32) };
        *self.lower.entry(key).or_insert(0.0) += value;
    }

    /// Stored entries of the lower triangle (diagonal included).
    pub fn stored(&self) -> usize {
        self.lower.len()
    }

    /// Entry (i, j), 0 where nothing was added.
    pub fn get(&self, i: usize, j: usize) -> f64 {
        let key = if i >= j { (i as u32, j as u32) } else { (j as u32, i as u32) };
        self.lower.get(&key).copied().unwrap_or(0.0)
    }

    /// Factorises the matrix (at most `max_envelope` stored factor entries) and solves for `rhs`.
    pub fn solve(&self, rhs: &[f64], max_envelope: usize) -> Result<Vec<f64>, SparseError> {
        Ok(self.factorise(max_envelope)?.solve(rhs))
    }

    /// The envelope Cholesky factor of the RCM-reordered matrix.
    pub fn factorise(&self, max_envelope: usize) -> Result<EnvelopeCholesky, SparseError> {
        if let Some((row, column)) = self.out_of_range {
            return Err(SparseError::OutOfRange { row, column, unknowns: self.unknowns });
        }
        let n = self.unknowns;
        let order = reverse_cuthill_mckee(n, self.lower.keys().map(|&(i, j)| (i as usize, j as usize)));
        let mut position = vec![0usize; n];
        for (new, &old) in order.iter().enumerate() {
            position[old] = new;
        }
        // Each reordered row's first column, then the rows' offsets in one array.
        let mut first: Vec<usize> = (0..n).collect();
        for &(i, j) in self.lower.keys() {
            let (a, b) = (position[i as usize], position[j as usize]);
            let (row, column) = if a >= b { (a, b) } else { (b, a) };
            first[row] = first[row].min(column);
        }
        let mut offset = Vec::with_capacity(n + 1);
        offset.push(0usize);
        for (i, &f) in first.iter().enumerate() {
            let next = offset[i] + (i - f + 1);
            if next > max_envelope {
                let entries = next + (i + 1..n).map(|r| r - first[r] + 1).sum::<usize>();
                return Err(SparseError::TooLarge { entries, limit: max_envelope });
            }
            offset.push(next);
        }
        let mut values = vec![0.0f64; offset[n]];
        for (&(i, j), &v) in &self.lower {
            let (a, b) = (position[i as usize], position[j as usize]);
            let (row, column) = if a >= b { (a, b) } else { (b, a) };
            values[offset[row] + column - first[row]] = v;
        }
        let mut factor = EnvelopeCholesky { first, offset, values, order };
        factor.factorise_in_place()?;
        Ok(factor)
    }
}

/// A Cholesky factor `L` (`P A Pᵀ = L Lᵀ`) stored row by row from each row's first non-zero
/// column to the diagonal.
#[derive(Clone, Debug)]
pub struct EnvelopeCholesky {
    first: Vec<usize>,
    offset: Vec<usize>,
    values: Vec<f64>,
    /// New position → original unknown.
    order: Vec<usize>,
}

impl EnvelopeCholesky {
    /// Stored factor entries.
    pub fn envelope(&self) -> usize {
        self.values.len()
    }

    /// Row-oriented (bordering) Cholesky: row i's entries are dot products of contiguous pieces of
    /// rows already factorised, and fill-in never leaves the envelope.
    fn factorise_in_place(&mut self) -> Result<(), SparseError> {
        let n = self.first.len();
        for i in 0..n {
            let (fi, oi) = (self.first[i], self.offset[i]);
            let (done, rest) = self.values.split_at_mut(oi);
            let row = &mut rest[..i - fi + 1];
            for j in fi..i {
                let (fj, oj) = (self.first[j], self.offset[j]);
                let lo = fi.max(fj);
                let lj = &done[oj + lo - fj..oj + j - fj];
                let li = &row[lo - fi..j - fi];
                let dot: f64 = li.iter().zip(lj).map(|(a, b)| a * b).sum();
                let diagonal = done[oj + j - fj];
                row[j - fi] = (row[j - fi] - dot) / diagonal;
            }
            let off: f64 = row[..i - fi].iter().map(|v| v * v).sum();
            let d = row[i - fi] - off;
            if !(d > 0.0 && d.is_finite()) {
                return Err(SparseError::NotPositiveDefinite { pivot: i, unknowns: n, value: d });
            }
            row[i - fi] = d.sqrt();
        }
        Ok(())
    }

    /// Solves `A x = rhs` (original order).
    pub fn solve(&self, rhs: &[f64]) -> Vec<f64> {
        let n = self.first.len();
        let mut y: Vec<f64> = self.order.iter().map(|&old| rhs[old]).collect();
        // L y' = y, row by row.
        for i in 0..n {
            let (fi, oi) = (self.first[i], self.offset[i]);
            let row = &self.values[oi..oi + i - fi + 1];
            let dot: f64 = row[..i - fi].iter().zip(&y[fi..i]).map(|(a, b)| a * b).sum();
            y[i] = (y[i] - dot) / row[i - fi];
        }
        // Lᵀ x = y', column by column from the last.
        for i in (0..n).rev() {
            let (fi, oi) = (self.first[i], self.offset[i]);
            let row = &self.values[oi..oi + i - fi + 1];
            y[i] /= row[i - fi];
            let xi = y[i];
            for (yk, l) in y[fi..i].iter_mut().zip(&row[..i - fi]) {
                *yk -= l * xi;
            }
        }
        let mut x = vec![0.0; n];
        for (new, &old) in self.order.iter().enumerate() {
            x[old] = y[new];
        }
        x
    }
}

/// Reverse Cuthill–McKee order of the graph whose edges are the off-diagonal `pairs`: every
/// connected component from a pseudo-peripheral start, breadth first with the neighbours by
/// ascending degree, and the whole order reversed. Deterministic for a given set of pairs.
pub fn reverse_cuthill_mckee(n: usize, pairs: impl Iterator<Item = (usize, usize)>) -> Vec<usize> {
    let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); n];
    for (i, j) in pairs {
        if i != j {
            neighbours[i].push(j as u32);
            neighbours[j].push(i as u32);
        }
    }
    for list in &mut neighbours {
        list.sort_unstable();
        list.dedup();
    }
    let degree: Vec<usize> = neighbours.iter().map(Vec::len).collect();
    for list in &mut neighbours {
        list.sort_by_key(|&v| (degree[v as usize], v));
    }
    let mut placed = vec![false; n];
    let mut order = Vec::with_capacity(n);
    let mut level = vec![usize::MAX; n];
    // Unplaced nodes by ascending degree: each component starts from its least connected node.
    let mut starts: Vec<usize> = (0..n).collect();
    starts.sort_by_key(|&v| (degree[v], v));
    for &seed in &starts {
        if placed[seed] {
            continue;
        }
        let start = pseudo_peripheral(seed, &neighbours, &degree, &mut level);
        let mut queue = VecDeque::from([start]);
        placed[start] = true;
        while let Some(v) = queue.pop_front() {
            order.push(v);
            for &w in &neighbours[v] {
                let w = w as usize;
                if !placed[w] {
                    placed[w] = true;
                    queue.push_back(w);
                }
            }
        }
    }
    order.reverse();
    order
}

/// A node of `seed`'s component far from the others (George–Liu): breadth first from the
/// current guess, then from the least connected node of the deepest level, while the depth grows.
fn pseudo_peripheral(seed: usize, neighbours: &[Vec<u32>], degree: &[usize], level: &mut [usize]) -> usize {
    let mut start = seed;
    let mut depth = 0;
    loop {
        let (deepest, d) = breadth_first_levels(start, neighbours, level);
        let candidate = deepest.into_iter().min_by_key(|&v| (degree[v], v)).unwrap_or(start);
        if d <= depth || candidate == start {
            return start;
        }
        depth = d;
        start = candidate;
    }
}

/// The nodes of the deepest breadth-first level from `start`, and that depth. `level` is scratch
/// (reset for the nodes reached before returning).
fn breadth_first_levels(start: usize, neighbours: &[Vec<u32>], level: &mut [usize]) -> (Vec<usize>, usize) {
    let mut reached = vec![start];
    level[start] = 0;
    let mut head = 0;
    while head < reached.len() {
        let v = reached[head];
        head += 1;
        for &w in &neighbours[v] {
            let w = w as usize;
            if level[w] == usize::MAX {
                level[w] = level[v] + 1;
                reached.push(w);
            }
        }
    }
    let depth = level[*reached.last().unwrap_or(&start)];
    let deepest = reached.iter().copied().filter(|&v| level[v] == depth).collect();
    for &v in &reached {
        level[v] = usize::MAX;
    }
    (deepest, depth)
}

/// A field-like system over a street network: nodes on a square grid of `blocks` × `blocks` city
/// blocks, five nodes of block between streets two nodes wide (15 m nodes: 30 m streets, 75 m
/// blocks), three unknowns per node, each node coupled to its eight grid neighbours on the
/// streets by a random positive semi-definite 3×3 block, plus a weak prior on every unknown.
/// Returns the system and a right-hand side.
pub fn street_network_system(blocks: usize, seed: u64) -> (SymmetricSparse, Vec<f64>) {
    let mut rng = crate::rng::SplitMix64::new(seed);
    let side = 7 * blocks + 2;
    let street = |x: usize, y: usize| x % 7 < 2 || y % 7 < 2;
    let mut index = vec![usize::MAX; side * side];
    let mut nodes = 0;
    for y in 0..side {
        for x in 0..side {
            if street(x, y) {
                index[y * side + x] = nodes;
                nodes += 1;
            }
        }
    }
    let mut m = SymmetricSparse::new(3 * nodes);
    for y in 0..side {
        for x in 0..side {
            let a = index[y * side + x];
            if a == usize::MAX {
                continue;
            }
            for (dx, dy) in [(1, 0), (0, 1), (1, 1), (-1, 1)] {
                let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                if nx < 0 || nx >= side as i64 || ny >= side as i64 {
                    continue;
                }
                let b = index[ny as usize * side + nx as usize];
                if b == usize::MAX {
                    continue;
                }
                // w (e_a − e_b)(e_a − e_b)ᵀ ⊗ u uᵀ with a random direction u.
                let u = [rng.uniform() - 0.5, rng.uniform() - 0.5, rng.uniform() - 0.5];
                let w = 1.0 + 1e3 * rng.uniform();
                for r in 0..3 {
                    for c in 0..3 {
                        let v = w * u[r] * u[c];
                        if r >= c {
                            m.add(3 * a + r, 3 * a + c, v);
                            m.add(3 * b + r, 3 * b + c, v);
                        }
                        m.add(3 * a + r, 3 * b + c, -v);
                    }
                }
            }
        }
    }
    for i in 0..3 * nodes {
        m.add(i, i, 1.0);
    }
    let rhs = (0..3 * nodes).map(|_| rng.uniform() - 0.5).collect();
    (m, rhs)
}

/// Figures of [`bench_street_network`].
#[derive(Clone, Debug, serde::Serialize)]
pub struct SparseBench {
    pub blocks: usize,
    pub unknowns: usize,
    /// Stored entries of the matrix's lower triangle.
    pub stored: usize,
    /// Stored entries of the factor after ordering.
    pub envelope: usize,
    /// Ordering, factorisation and solve, seconds on the calling thread.
    pub sparse_s: f64,
    /// nalgebra's dense Cholesky of the same system, where it has at most 6,000 unknowns.
    pub dense_s: Option<f64>,
    /// Largest difference between the two solutions over the largest entry.
    pub dense_relative_difference: Option<f64>,
}

/// Solves [`street_network_system`] with the envelope Cholesky, and with a dense Cholesky where it
/// is small enough to form.
pub fn bench_street_network(blocks: usize) -> Result<SparseBench, SparseError> {
    let (m, rhs) = street_network_system(blocks, 0x5EED);
    let n = m.unknowns();
    let start = std::time::Instant::now();
    let factor = m.factorise(usize::MAX)?;
    let x = std::hint::black_box(factor.solve(&rhs));
    let sparse_s = start.elapsed().as_secs_f64();
    let (mut dense_s, mut dense_relative_difference) = (None, None);
    if n <= 6_000 {
        let mut dense = nalgebra::DMatrix::<f64>::zeros(n, n);
        for (&(i, j), &v) in &m.lower {
            dense[(i as usize, j as usize)] = v;
            dense[(j as usize, i as usize)] = v;
        }
        let b = nalgebra::DVector::from_vec(rhs);
        let start = std::time::Instant::now();
        let chol = nalgebra::Cholesky::new(dense).ok_or(SparseError::NotPositiveDefinite {
            pivot: 0,
            unknowns: n,
            value: f64::NAN,
        })?;
        let y = std::hint::black_box(chol.solve(&b));
        dense_s = Some(start.elapsed().as_secs_f64());
        let scale = y.amax().max(f64::MIN_POSITIVE);
        dense_relative_difference =
            Some(x.iter().zip(y.iter()).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max) / scale);
    }
    Ok(SparseBench {
        blocks,
        unknowns: n,
        stored: m.stored(),
        envelope: factor.envelope(),
        sparse_s,
        dense_s,
        dense_relative_difference,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64 as Rng;

    /// A random SPD matrix with the sparsity of a 2D grid (each unknown coupled to its grid
    /// neighbours), in shuffled numbering, plus a few isolated components.
    fn grid_system(side: usize, seed: u64) -> (SymmetricSparse, nalgebra::DMatrix<f64>) {
        let mut rng = Rng::new(seed);
        let n = side * side + 3;
        let mut label: Vec<usize> = (0..n).collect();
        for i in (1..n).rev() {
            let j = (rng.uniform() * (i + 1) as f64) as usize % (i + 1);
            label.swap(i, j);
        }
        let mut sparse = SymmetricSparse::new(n);
        let mut dense = nalgebra::DMatrix::<f64>::zeros(n, n);
        let mut couple = |a: usize, b: usize, w: f64| {
            // w (e_a − e_b)(e_a − e_b)ᵀ: positive semi-definite, the diagonal makes it definite.
            let (a, b) = (label[a], label[b]);
            for (i, j, v) in [(a, a, w), (b, b, w), (a, b, -w)] {
                sparse.add(i, j, v);
                dense[(i, j)] += v;
                if i != j {
                    dense[(j, i)] += v;
                }
            }
        };
        for r in 0..side {
            for c in 0..side {
                let k = r * side + c;
                if c + 1 < side {
                    couple(k, k + 1, 1.0 + rng.uniform() * 1e3);
                }
                if r + 1 < side {
                    couple(k, k + side, 1.0 + rng.uniform() * 1e3);
                }
            }
        }
        for i in 0..n {
            let d = 1e-2 + rng.uniform();
            sparse.add(label[i], label[i], d);
            dense[(label[i], label[i])] += d;
        }
        (sparse, dense)
    }

    #[test]
    fn envelope_cholesky_equals_the_dense_solve() {
        for (side, seed) in [(1, 1), (2, 2), (5, 3), (12, 4), (30, 5)] {
            let (sparse, dense) = grid_system(side, seed);
            let n = sparse.unknowns();
            let mut rng = Rng::new(seed + 100);
            let rhs: Vec<f64> = (0..n).map(|_| rng.uniform() - 0.5).collect();
            let x = sparse.solve(&rhs, usize::MAX).unwrap();
            let reference =
                nalgebra::Cholesky::new(dense.clone()).unwrap().solve(&nalgebra::DVector::from_vec(rhs.clone()));
            let scale = reference.amax();
            for (a, b) in x.iter().zip(reference.iter()) {
                assert!((a - b).abs() <= 1e-9 * scale, "side {side}: {a} vs {b}");
            }
            // And the residual of the original (unordered) system is small.
            let r = &dense * nalgebra::DVector::from_vec(x) - nalgebra::DVector::from_vec(rhs);
            assert!(r.amax() < 1e-8, "side {side}: residual {}", r.amax());
        }
    }

    #[test]
    fn rcm_keeps_a_grid_envelope_near_its_width() {
        // A 30 × 30 grid in shuffled numbering: RCM's envelope is about n × side (the dense
        // lower triangle would be n²/2, a random order far more than n × side).
        let (sparse, _) = grid_system(30, 7);
        let factor = sparse.factorise(usize::MAX).unwrap();
        let n = sparse.unknowns();
        assert!(factor.envelope() < 2 * n * 30, "envelope {} for {n} unknowns", factor.envelope());
        assert!(factor.envelope() < n * n / 8);
    }

    #[test]
    fn rcm_orders_every_node_once_across_components() {
        let order = reverse_cuthill_mckee(7, [(0, 1), (1, 2), (4, 5), (3, 3)].into_iter());
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..7).collect::<Vec<_>>());
        // A path stays a path: its neighbours stay adjacent in the order.
        let at = |v: usize| order.iter().position(|&o| o == v).unwrap() as i64;
        assert_eq!((at(0) - at(1)).abs(), 1);
        assert_eq!((at(1) - at(2)).abs(), 1);
        assert_eq!((at(4) - at(5)).abs(), 1);
    }

    #[test]
    fn indefinite_too_large_and_out_of_range_systems_are_errors() {
        let mut m = SymmetricSparse::new(2);
        m.add(0, 0, 1.0);
        m.add(1, 1, 1.0);
        m.add(0, 1, 2.0);
        assert!(matches!(m.solve(&[1.0, 1.0], usize::MAX), Err(SparseError::NotPositiveDefinite { pivot: 1, .. })));
        let mut nan = SymmetricSparse::new(1);
        nan.add(0, 0, f64::NAN);
        assert!(matches!(nan.solve(&[1.0], usize::MAX), Err(SparseError::NotPositiveDefinite { .. })));
        let (sparse, _) = grid_system(12, 9);
        let err = sparse.factorise(100).unwrap_err();
        assert!(matches!(err, SparseError::TooLarge { limit: 100, entries } if entries > 100), "{err}");
        let mut out = SymmetricSparse::new(2);
        out.add(2, 0, 1.0);
        assert_eq!(
            out.solve(&[0.0; 2], usize::MAX).unwrap_err(),
            SparseError::OutOfRange { row: 2, column: 0, unknowns: 2 }
        );
    }

    #[test]
    fn street_network_system_solves_like_the_dense_solve() {
        let (sparse, rhs) = street_network_system(3, 11);
        let n = sparse.unknowns();
        let mut dense = nalgebra::DMatrix::<f64>::zeros(n, n);
        for i in 0..n {
            for j in 0..=i {
                let v = sparse.get(i, j);
                dense[(i, j)] = v;
                dense[(j, i)] = v;
            }
        }
        let x = sparse.solve(&rhs, usize::MAX).unwrap();
        let r = &dense * nalgebra::DVector::from_vec(x) - nalgebra::DVector::from_vec(rhs);
        assert!(r.amax() < 1e-9, "residual {}", r.amax());
    }
}
