//! Exact solve of a sparse symmetric positive definite system: a nested-dissection ordering, then
//! a sparse Cholesky factorisation (elimination tree, row patterns by `ereach`, up-looking
//! numeric factorisation) that stores only the factor's non-zeros.
//!
//! Written for the common-mode field (`precimap_estimate::field`): its unknowns are the nodes of a
//! grid laid over the streets, coupled only to the nodes near them. Nested dissection orders each
//! half of the network before the separator between them, recursively, so the factor's fill stays
//! near O(n log n) entries and its work near O(n^1.5) for such planar-like networks. The field
//! knows its nodes' positions and cuts the network straight where the cut crosses the fewest
//! couplings ([`SymmetricSparse::factorise_at`]); without positions the separators are level
//! sets of a breadth-first search ([`SymmetricSparse::factorise`]). The reverse Cuthill–McKee
//! envelope this replaced held O(n × network width) entries: 1 GiB at ~40 km² of
//! 15 m nodes, where a city campaign had to coarsen its field.

use std::collections::HashMap;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SparseError {
    #[error("the system is not positive definite: pivot {pivot} of {unknowns} is {value:e}")]
    NotPositiveDefinite { pivot: usize, unknowns: usize, value: f64 },
    #[error("the system's factor holds {entries} entries after ordering, more than the {limit} it may use")]
    TooLarge { entries: usize, limit: usize },
    #[error("entry ({row}, {column}) lies outside the {unknowns} unknowns")]
    OutOfRange { row: usize, column: usize, unknowns: usize },
    #[error("{given} coordinates for {unknowns} unknowns")]
    Coordinates { given: usize, unknowns: usize },
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

    /// The stored entries of the lower triangle as `(row, column, value)` with `row ≥ column`,
    /// in no particular order.
    pub fn lower_entries(&self) -> impl Iterator<Item = (usize, usize, f64)> + '_ {
        self.lower.iter().map(|(&(i, j), &v)| (i as usize, j as usize, v))
    }

    /// Entry (i, j), 0 where nothing was added.
    pub fn get(&self, i: usize, j: usize) -> f64 {
        let key = if i >= j { (i as u32, j as u32) } else { (j as u32, i as u32) };
        self.lower.get(&key).copied().unwrap_or(0.0)
    }

    /// Factorises the matrix (at most `max_entries` stored factor entries) and solves for `rhs`.
    pub fn solve(&self, rhs: &[f64], max_entries: usize) -> Result<Vec<f64>, SparseError> {
        Ok(self.factorise(max_entries)?.solve(rhs))
    }

    /// The Cholesky factor of the matrix in nested-dissection order, refused (before any of it
    /// is allocated) if it would hold more than `max_entries` entries.
    pub fn factorise(&self, max_entries: usize) -> Result<SparseCholesky, SparseError> {
        let order = nested_dissection(self.unknowns, self.pairs()?);
        self.factorise_in(order, max_entries)
    }

    /// [`Self::factorise`] with each unknown's position in the plane (`coordinates`, one per
    /// unknown): the separators are straight cuts where they cross the fewest couplings
    /// ([`geometric_nested_dissection`]).
    pub fn factorise_at(&self, max_entries: usize, coordinates: &[[f64; 2]]) -> Result<SparseCholesky, SparseError> {
        let pairs = self.pairs()?;
        if coordinates.len() != self.unknowns {
            return Err(SparseError::Coordinates { given: coordinates.len(), unknowns: self.unknowns });
        }
        let order = geometric_nested_dissection(coordinates, pairs);
        self.factorise_in(order, max_entries)
    }

    /// The off-diagonal structure, as pairs of unknowns; an error if an entry was added outside
    /// the unknowns (the orderings index arrays by them).
    fn pairs(&self) -> Result<impl Iterator<Item = (usize, usize)> + '_, SparseError> {
        if let Some((row, column)) = self.out_of_range {
            return Err(SparseError::OutOfRange { row, column, unknowns: self.unknowns });
        }
        Ok(self.lower.keys().map(|&(i, j)| (i as usize, j as usize)))
    }

    /// The factor in the given order (new position → original unknown).
    fn factorise_in(&self, order: Vec<usize>, max_entries: usize) -> Result<SparseCholesky, SparseError> {
        let n = self.unknowns;
        let mut position = vec![0u32; n];
        for (new, &old) in order.iter().enumerate() {
            position[old] = new as u32;
        }
        // The reordered lower triangle by rows (row k: its columns ≤ k), in a fixed order: the
        // hash map's order would make the sums below differ in their last bits between runs.
        let mut entries: Vec<(u32, u32, f64)> = self
            .lower
            .iter()
            .map(|(&(i, j), &v)| {
                let (a, b) = (position[i as usize], position[j as usize]);
                if a >= b {
                    (a, b, v)
                } else {
                    (b, a, v)
                }
            })
            .collect();
        entries.sort_unstable_by_key(|&(r, c, _)| (r, c));
        let mut row_start = vec![0usize; n + 1];
        for &(r, ..) in &entries {
            row_start[r as usize + 1] += 1;
        }
        for k in 0..n {
            row_start[k + 1] += row_start[k];
        }
        let columns: Vec<u32> = entries.iter().map(|e| e.1).collect();
        let values: Vec<f64> = entries.iter().map(|e| e.2).collect();
        drop(entries);
        let rows = LowerRows { start: row_start, column: columns, value: values };
        let mut factor = SparseCholesky::symbolic(&rows, order, max_entries)?;
        factor.numeric(&rows)?;
        Ok(factor)
    }
}

/// A lower triangle stored by rows (row k's columns rise, the last may be k itself).
struct LowerRows {
    start: Vec<usize>,
    column: Vec<u32>,
    value: Vec<f64>,
}

impl LowerRows {
    fn row(&self, k: usize) -> (&[u32], &[f64]) {
        let (s, e) = (self.start[k], self.start[k + 1]);
        (&self.column[s..e], &self.value[s..e])
    }
}

const NONE: u32 = u32::MAX;

/// A Cholesky factor `L` (`P A Pᵀ = L Lᵀ`) stored by columns, each column's diagonal first.
#[derive(Clone, Debug)]
pub struct SparseCholesky {
    /// Column j holds entries `start[j]..start[j + 1]`.
    start: Vec<usize>,
    row: Vec<u32>,
    value: Vec<f64>,
    /// Elimination tree: the parent of each column, [`NONE`] for roots.
    parent: Vec<u32>,
    /// New position → original unknown.
    order: Vec<usize>,
}

/// Row k's pattern in `L` (the columns j < k with `L[k][j] ≠ 0`), each column before its
/// elimination-tree ancestors: the columns reached from row k's entries climbing the tree until
/// a column already reached (Liu; CSparse's `ereach`). `flag` marks the reached columns with k,
/// `path` and `stack` are scratch of n entries; the pattern is `stack[top..]`.
fn row_pattern(
    k: usize,
    columns: &[u32],
    parent: &[u32],
    flag: &mut [u32],
    path: &mut [u32],
    stack: &mut [u32],
) -> usize {
    let n = stack.len();
    let mut top = n;
    flag[k] = k as u32;
    for &j in columns {
        let mut i = j;
        let mut len = 0;
        // Every column of row k has k as an ancestor, where the climb stops at the latest.
        while i != NONE && flag[i as usize] != k as u32 {
            path[len] = i;
            len += 1;
            flag[i as usize] = k as u32;
            i = parent[i as usize];
        }
        while len > 0 {
            len -= 1;
            top -= 1;
            stack[top] = path[len];
        }
    }
    top
}

impl SparseCholesky {
    /// Stored factor entries.
    pub fn entries(&self) -> usize {
        self.value.len()
    }

    /// Elimination tree and column counts; the factor's arrays, allocated only within the limit.
    fn symbolic(rows: &LowerRows, order: Vec<usize>, max_entries: usize) -> Result<Self, SparseError> {
        let n = order.len();
        let mut parent = vec![NONE; n];
        let mut ancestor = vec![NONE; n];
        for k in 0..n {
            for &j in rows.row(k).0 {
                // Climb from j to its current root, compressing the path onto k.
                let mut i = j;
                while i != NONE && (i as usize) < k {
                    let next = ancestor[i as usize];
                    ancestor[i as usize] = k as u32;
                    if next == NONE {
                        parent[i as usize] = k as u32;
                    }
                    i = next;
                }
            }
        }
        drop(ancestor);
        let (mut flag, mut path, mut stack) = (vec![NONE; n], vec![0u32; n], vec![0u32; n]);
        // Each column's diagonal, plus one entry per row whose pattern holds it.
        let mut count = vec![1usize; n];
        for k in 0..n {
            let top = row_pattern(k, rows.row(k).0, &parent, &mut flag, &mut path, &mut stack);
            for &j in &stack[top..] {
                count[j as usize] += 1;
            }
        }
        let entries: usize = count.iter().sum();
        if entries > max_entries {
            return Err(SparseError::TooLarge { entries, limit: max_entries });
        }
        let mut start = Vec::with_capacity(n + 1);
        start.push(0usize);
        for &c in &count {
            start.push(start.last().copied().unwrap_or(0) + c);
        }
        Ok(Self { start, row: vec![0; entries], value: vec![0.0; entries], parent, order })
    }

    /// Up-looking factorisation: row k of `L` solves `L[..k][..k] l = A[..k][k]` over row k's
    /// pattern, each column in the pattern before its ancestors (CSparse's `cs_chol`).
    fn numeric(&mut self, rows: &LowerRows) -> Result<(), SparseError> {
        let n = self.order.len();
        let (mut flag, mut path, mut stack) = (vec![NONE; n], vec![0u32; n], vec![0u32; n]);
        // Next free entry of each column (its diagonal comes first).
        let mut next: Vec<usize> = self.start[..n].iter().map(|s| s + 1).collect();
        let mut x = vec![0.0f64; n];
        for k in 0..n {
            let (columns, values) = rows.row(k);
            let top = row_pattern(k, columns, &self.parent, &mut flag, &mut path, &mut stack);
            for (&j, &v) in columns.iter().zip(values) {
                x[j as usize] = v;
            }
            let mut d = x[k];
            x[k] = 0.0;
            for &j in &stack[top..] {
                let j = j as usize;
                let (first, end) = (self.start[j], next[j]);
                let lkj = x[j] / self.value[first];
                x[j] = 0.0;
                for p in first + 1..end {
                    x[self.row[p] as usize] -= self.value[p] * lkj;
                }
                d -= lkj * lkj;
                self.row[end] = k as u32;
                self.value[end] = lkj;
                next[j] = end + 1;
            }
            if !(d > 0.0 && d.is_finite()) {
                return Err(SparseError::NotPositiveDefinite { pivot: k, unknowns: n, value: d });
            }
            let first = self.start[k];
            self.row[first] = k as u32;
            self.value[first] = d.sqrt();
        }
        Ok(())
    }

    /// Solves `A x = rhs` (original order).
    pub fn solve(&self, rhs: &[f64]) -> Vec<f64> {
        let n = self.order.len();
        let mut y: Vec<f64> = self.order.iter().map(|&old| rhs[old]).collect();
        // L y' = y, column by column.
        for j in 0..n {
            let (first, end) = (self.start[j], self.start[j + 1]);
            y[j] /= self.value[first];
            let yj = y[j];
            for p in first + 1..end {
                y[self.row[p] as usize] -= self.value[p] * yj;
            }
        }
        // Lᵀ x = y', from the last column.
        for j in (0..n).rev() {
            let (first, end) = (self.start[j], self.start[j + 1]);
            let dot: f64 = (first + 1..end).map(|p| self.value[p] * y[self.row[p] as usize]).sum();
            y[j] = (y[j] - dot) / self.value[first];
        }
        let mut x = vec![0.0; n];
        for (new, &old) in self.order.iter().enumerate() {
            x[old] = y[new];
        }
        x
    }
}

/// Parts of at most this many unknowns are not dissected further: their own fill is small.
const LEAF_UNKNOWNS: usize = 64;

/// The graph of the off-diagonal pairs, as sorted, de-duplicated neighbour lists.
struct Graph {
    start: Vec<usize>,
    neighbour: Vec<u32>,
}

impl Graph {
    fn new(n: usize, pairs: impl Iterator<Item = (usize, usize)>) -> Self {
        let edges: Vec<(u32, u32)> = pairs.filter(|&(i, j)| i != j).map(|(i, j)| (i as u32, j as u32)).collect();
        let mut start = vec![0usize; n + 1];
        for &(i, j) in &edges {
            start[i as usize + 1] += 1;
            start[j as usize + 1] += 1;
        }
        for v in 0..n {
            start[v + 1] += start[v];
        }
        let mut fill = start.clone();
        let mut neighbour = vec![0u32; start[n]];
        for &(i, j) in &edges {
            neighbour[fill[i as usize]] = j;
            fill[i as usize] += 1;
            neighbour[fill[j as usize]] = i;
            fill[j as usize] += 1;
        }
        drop(edges);
        // Sorted and de-duplicated in place, the lists compacted to the front.
        let mut compact = Vec::with_capacity(n + 1);
        compact.push(0usize);
        let mut write = 0;
        for v in 0..n {
            let (s, e) = (start[v], start[v + 1]);
            neighbour[s..e].sort_unstable();
            let mut last = NONE;
            for r in s..e {
                let w = neighbour[r];
                if w != last {
                    neighbour[write] = w;
                    write += 1;
                    last = w;
                }
            }
            compact.push(write);
        }
        neighbour.truncate(write);
        Self { start: compact, neighbour }
    }

    fn neighbours(&self, v: usize) -> &[u32] {
        &self.neighbour[self.start[v]..self.start[v + 1]]
    }
}

/// Nested-dissection order of the graph whose edges are the off-diagonal `pairs` (George's
/// automatic nested dissection by level structures): from a pseudo-peripheral node of each
/// connected part, breadth-first levels; a small level near the middle separates the levels
/// before it from those after it; both sides are ordered first (recursively), the separator
/// last. Parts of at most [`LEAF_UNKNOWNS`] stay as they are. Deterministic for a given set of
/// pairs.
pub fn nested_dissection(n: usize, pairs: impl Iterator<Item = (usize, usize)>) -> Vec<usize> {
    let graph = Graph::new(n, pairs);
    let mut d = Dissection { graph: &graph, region: vec![0; n], next_region: 1, level: vec![u32::MAX; n] };
    dissection_order(n, |nodes| d.split(nodes))
}

/// How a part of a nested dissection splits: `parts` are ordered first, in this order, then the
/// `separator`.
struct Split {
    parts: Vec<Vec<u32>>,
    separator: Vec<u32>,
}

/// The order of a nested dissection of unknowns `0..n`: every part of more than
/// [`LEAF_UNKNOWNS`] is split by `split` (a part with nothing to split returns no parts and
/// itself as the separator), smaller parts stay as they are. On a work stack, not by recursion: a
/// graph split unevenly may nest deeper than a thread's stack allows.
fn dissection_order(n: usize, mut split: impl FnMut(Vec<u32>) -> Split) -> Vec<usize> {
    enum Work {
        Dissect(Vec<u32>),
        Place(Vec<u32>),
    }
    let mut order = Vec::with_capacity(n);
    let mut work = vec![Work::Dissect((0..n as u32).collect())];
    while let Some(next) = work.pop() {
        match next {
            Work::Place(nodes) => order.extend(nodes.iter().map(|&v| v as usize)),
            Work::Dissect(nodes) if nodes.len() <= LEAF_UNKNOWNS => order.extend(nodes.iter().map(|&v| v as usize)),
            Work::Dissect(nodes) => {
                let Split { parts, separator } = split(nodes);
                // Popped in reverse: the parts in their order, then the separator.
                work.push(Work::Place(separator));
                work.extend(parts.into_iter().rev().map(Work::Dissect));
            }
        }
    }
    order
}

/// Nested-dissection order of the graph of `pairs` whose unknowns lie at `coordinates`. Each part
/// is sorted along its longer extent and cut straight, at the position within its middle 40 %
/// whose boundary (the unknowns of one side coupled to the other) is smallest; that boundary is
/// the separator. Both sides are ordered first (on a work stack), the separator last, down to
/// parts of [`LEAF_UNKNOWNS`]. On a street network such a cut crosses the streets between two
/// blocks, where the median cut may run along a street. Deterministic for a given set of pairs.
pub fn geometric_nested_dissection(
    coordinates: &[[f64; 2]],
    pairs: impl Iterator<Item = (usize, usize)>,
) -> Vec<usize> {
    let n = coordinates.len();
    let graph = Graph::new(n, pairs);
    // Each unknown's part (a fresh label per part being cut) and rank along the cut's axis.
    let (mut part, mut rank) = (vec![0u32; n], vec![0u32; n]);
    let mut next_part = 1u32;
    dissection_order(n, |mut nodes| {
        let label = next_part;
        next_part += 1;
        for &v in &nodes {
            part[v as usize] = label;
        }
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for &v in &nodes {
            for axis in 0..2 {
                lo[axis] = lo[axis].min(coordinates[v as usize][axis]);
                hi[axis] = hi[axis].max(coordinates[v as usize][axis]);
            }
        }
        let axis = usize::from(hi[1] - lo[1] > hi[0] - lo[0]);
        let key = |v: u32| coordinates[v as usize][axis];
        nodes.sort_unstable_by(|&a, &b| key(a).total_cmp(&key(b)).then(a.cmp(&b)));
        for (r, &v) in nodes.iter().enumerate() {
            rank[v as usize] = r as u32;
        }
        // Cut i puts ranks < i on the left. Unknown u (rank p) is on the left boundary of the
        // cuts p + 1 ..= (its farthest neighbour's rank), on the right boundary of the cuts
        // (its nearest neighbour's rank) + 1 ..= p: difference arrays over the cuts.
        let m = nodes.len();
        let (mut left, mut right) = (vec![0i64; m + 2], vec![0i64; m + 2]);
        for &v in &nodes {
            let p = rank[v as usize] as usize;
            let (mut near, mut far) = (p, p);
            for &w in graph.neighbours(v as usize) {
                if part[w as usize] == label {
                    let q = rank[w as usize] as usize;
                    near = near.min(q);
                    far = far.max(q);
                }
            }
            if far > p {
                left[p + 1] += 1;
                left[far + 1] -= 1;
            }
            if near < p {
                right[near + 1] += 1;
                right[p + 1] -= 1;
            }
        }
        let (mut in_left, mut in_right) = (0i64, 0i64);
        // (separator size, distance from the middle, cut, separator on the left)
        let mut best: Option<(i64, usize, usize, bool)> = None;
        for i in 1..m {
            in_left += left[i];
            in_right += right[i];
            // Only between distinct positions: unknowns at one place stay on one side.
            if 10 * i < 3 * m || 10 * i > 7 * m || key(nodes[i - 1]) == key(nodes[i]) {
                continue;
            }
            let candidate = (in_left.min(in_right), i.abs_diff(m / 2), i, in_left <= in_right);
            if best.is_none_or(|b| (candidate.0, candidate.1) < (b.0, b.1)) {
                best = Some(candidate);
            }
        }
        // No distinct positions in the middle (a part stacked on one spot): cut at the middle.
        let (cut, separator_left) = best.map_or((m / 2, true), |b| (b.2, b.3));
        let right_side = nodes.split_off(cut);
        let left_side = nodes;
        let (boundary_side, other_side) =
            if separator_left { (left_side, right_side) } else { (right_side, left_side) };
        let other_ranks = if separator_left { cut as u32..m as u32 } else { 0..cut as u32 };
        let (separator, inside): (Vec<u32>, Vec<u32>) = boundary_side.into_iter().partition(|&v| {
            graph
                .neighbours(v as usize)
                .iter()
                .any(|&w| part[w as usize] == label && other_ranks.contains(&rank[w as usize]))
        });
        Split { parts: vec![inside, other_side], separator }
    })
}

struct Dissection<'a> {
    graph: &'a Graph,
    /// Each node's current part: every node of a part carries its label.
    region: Vec<u32>,
    next_region: u32,
    /// Breadth-first level scratch ([`u32::MAX`] outside a search).
    level: Vec<u32>,
}

impl Dissection<'_> {
    /// Splits `nodes` (a part: all of one region) at a breadth-first level. Nodes the search does
    /// not reach (other connected parts) are a part of their own; ordered before the separator,
    /// they share no edge with it, so the fill is the same.
    fn split(&mut self, nodes: Vec<u32>) -> Split {
        let id = self.region[nodes[0] as usize];
        let (reached, levels, depth) = self.pseudo_peripheral(nodes[0], id);
        let rest: Vec<u32> = if reached.len() < nodes.len() {
            // The reached nodes marked in the level scratch for the moment.
            for &v in &reached {
                self.level[v as usize] = 0;
            }
            let rest = nodes.iter().copied().filter(|&v| self.level[v as usize] == u32::MAX).collect();
            self.level_of(&reached);
            rest
        } else {
            Vec::new()
        };
        drop(nodes);
        if depth < 2 || reached.len() <= LEAF_UNKNOWNS {
            return Split { parts: vec![rest], separator: reached };
        }
        let separator_level = choose_separator(&levels, depth as usize) as u32;
        let (a, b) = (self.next_region, self.next_region + 1);
        self.next_region += 2;
        let (mut before, mut after, mut separator) = (Vec::new(), Vec::new(), Vec::new());
        for (&v, &l) in reached.iter().zip(&levels) {
            if l < separator_level {
                self.region[v as usize] = a;
                before.push(v);
            } else if l > separator_level {
                self.region[v as usize] = b;
                after.push(v);
            } else {
                separator.push(v);
            }
        }
        Split { parts: vec![before, after, rest], separator }
    }

    /// The nodes of region `id` reachable from `start`, in breadth-first order, and the depth;
    /// `level` holds their levels until [`Self::level_of`] reads and clears them.
    fn levels(&mut self, start: u32, id: u32) -> (Vec<u32>, u32) {
        let mut reached = vec![start];
        self.level[start as usize] = 0;
        let mut head = 0;
        while head < reached.len() {
            let v = reached[head] as usize;
            head += 1;
            let next = self.level[v] + 1;
            for &w in self.graph.neighbours(v) {
                let w = w as usize;
                if self.region[w] == id && self.level[w] == u32::MAX {
                    self.level[w] = next;
                    reached.push(w as u32);
                }
            }
        }
        let depth = self.level[*reached.last().unwrap_or(&start) as usize];
        (reached, depth)
    }

    /// The levels of `reached`, cleared from the scratch.
    fn level_of(&mut self, reached: &[u32]) -> Vec<u32> {
        reached.iter().map(|&v| std::mem::replace(&mut self.level[v as usize], u32::MAX)).collect()
    }

    /// The level structure from a node of `seed`'s connected part of region `id` far from the
    /// others (George–Liu: breadth first from the current guess, then from the least connected
    /// node of the deepest level, while the depth grows): the nodes reached in breadth-first
    /// order, their levels and the depth. The last search is the one returned, not run again.
    fn pseudo_peripheral(&mut self, seed: u32, id: u32) -> (Vec<u32>, Vec<u32>, u32) {
        let (mut start, mut depth) = (seed, 0);
        loop {
            let (reached, d) = self.levels(start, id);
            let levels = self.level_of(&reached);
            let degree = |v: u32| self.graph.neighbours(v as usize).len();
            let candidate = reached
                .iter()
                .zip(&levels)
                .filter(|&(_, &l)| l == d)
                .map(|(&v, _)| v)
                .min_by_key(|&v| (degree(v), v))
                .unwrap_or(start);
            if d <= depth || candidate == start {
                return (reached, levels, d);
            }
            depth = d;
            start = candidate;
        }
    }
}

/// The separating level: the smallest of those with at least 30 % of the nodes on either side
/// (the most balanced one if none has), never the first or the last, so both sides hold nodes.
fn choose_separator(levels: &[u32], depth: usize) -> usize {
    let mut size = vec![0usize; depth + 1];
    for &l in levels {
        size[l as usize] += 1;
    }
    let total = levels.len();
    let mut best: Option<(usize, usize)> = None;
    let mut balanced = (usize::MAX, 1);
    let mut before = size[0];
    for (l, &s) in size.iter().enumerate().take(depth).skip(1) {
        let after = total - before - s;
        let imbalance = before.abs_diff(after);
        if imbalance < balanced.0 {
            balanced = (imbalance, l);
        }
        if 10 * before >= 3 * total && 10 * after >= 3 * total && best.is_none_or(|(bs, _)| s < bs) {
            best = Some((s, l));
        }
        before += s;
    }
    best.map_or(balanced.1, |(_, l)| l)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64 as Rng;

    /// A random SPD matrix with the sparsity of a 2D grid (each unknown coupled to its grid
    /// neighbours), in shuffled numbering, plus a few isolated components; and each unknown's
    /// grid position (the isolated ones on a row of their own).
    fn grid_system(side: usize, seed: u64) -> (SymmetricSparse, nalgebra::DMatrix<f64>, Vec<[f64; 2]>) {
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
        let mut coordinates = vec![[0.0; 2]; n];
        for i in 0..n {
            let d = 1e-2 + rng.uniform();
            sparse.add(label[i], label[i], d);
            dense[(label[i], label[i])] += d;
            coordinates[label[i]] = [(i % side) as f64, (i / side) as f64];
        }
        (sparse, dense, coordinates)
    }

    #[test]
    fn sparse_cholesky_equals_the_dense_solve() {
        for (side, seed) in [(1, 1), (2, 2), (5, 3), (12, 4), (30, 5)] {
            let (sparse, dense, coordinates) = grid_system(side, seed);
            let n = sparse.unknowns();
            let mut rng = Rng::new(seed + 100);
            let rhs: Vec<f64> = (0..n).map(|_| rng.uniform() - 0.5).collect();
            let reference =
                nalgebra::Cholesky::new(dense.clone()).unwrap().solve(&nalgebra::DVector::from_vec(rhs.clone()));
            let scale = reference.amax();
            // Ordered by level structures, and by straight cuts at the unknowns' positions.
            let by_levels = sparse.solve(&rhs, usize::MAX).unwrap();
            let by_cuts = sparse.factorise_at(usize::MAX, &coordinates).unwrap().solve(&rhs);
            for x in [by_levels, by_cuts] {
                for (a, b) in x.iter().zip(reference.iter()) {
                    assert!((a - b).abs() <= 1e-9 * scale, "side {side}: {a} vs {b}");
                }
                // And the residual of the original (unordered) system is small.
                let r = &dense * nalgebra::DVector::from_vec(x) - nalgebra::DVector::from_vec(rhs.clone());
                assert!(r.amax() < 1e-8, "side {side}: residual {}", r.amax());
            }
        }
    }

    #[test]
    fn nested_dissection_keeps_a_grid_factor_far_below_its_envelope() {
        // A 60 × 60 grid in shuffled numbering. Reverse Cuthill–McKee's envelope (the solver
        // it replaced) is about n × side entries; nested dissection's factor grows as
        // n log n, and the factor must still solve the system exactly.
        let side = 60;
        let (sparse, dense, coordinates) = grid_system(side, 7);
        let n = sparse.unknowns();
        let rhs: Vec<f64> = (0..n).map(|i| (i % 7) as f64 - 3.0).collect();
        for factor in [sparse.factorise(usize::MAX).unwrap(), sparse.factorise_at(usize::MAX, &coordinates).unwrap()] {
            assert!(factor.entries() < n * side / 2, "{} factor entries for {n} unknowns", factor.entries());
            let x = factor.solve(&rhs);
            let r = &dense * nalgebra::DVector::from_vec(x) - nalgebra::DVector::from_vec(rhs.clone());
            assert!(r.amax() < 1e-8, "residual {}", r.amax());
        }
    }

    #[test]
    fn nested_dissection_orders_every_node_once_across_components() {
        // Two grids (one large enough to be dissected), a path, isolated nodes and a self-pair.
        let mut pairs = Vec::new();
        let grid = |offset: usize, side: usize, pairs: &mut Vec<(usize, usize)>| {
            for r in 0..side {
                for c in 0..side {
                    let k = offset + r * side + c;
                    if c + 1 < side {
                        pairs.push((k, k + 1));
                    }
                    if r + 1 < side {
                        pairs.push((k + side, k));
                    }
                }
            }
        };
        grid(0, 25, &mut pairs);
        grid(625, 5, &mut pairs);
        pairs.extend([(650, 651), (651, 652), (653, 653)]);
        let n = 660;
        // Positions: the grids side by side, the rest on a line (some of them on one spot).
        let coordinates: Vec<[f64; 2]> = (0..n)
            .map(|k| match k {
                0..625 => [(k % 25) as f64, (k / 25) as f64],
                625..650 => [30.0 + ((k - 625) % 5) as f64, ((k - 625) / 5) as f64],
                _ => [40.0 + (k % 3) as f64, 0.0],
            })
            .collect();
        for order in [
            nested_dissection(n, pairs.iter().copied()),
            geometric_nested_dissection(&coordinates, pairs.iter().copied()),
        ] {
            let mut sorted = order.clone();
            sorted.sort_unstable();
            assert_eq!(sorted, (0..n).collect::<Vec<_>>());
        }
        assert_eq!(nested_dissection(n, pairs.iter().copied()), nested_dissection(n, pairs.iter().rev().copied()));
        assert_eq!(
            geometric_nested_dissection(&coordinates, pairs.iter().copied()),
            geometric_nested_dissection(&coordinates, pairs.iter().rev().copied())
        );
        // Every unknown on one spot: no cut between positions, still a permutation.
        let stacked = geometric_nested_dissection(&vec![[1.0, 2.0]; 300], (1..300).map(|k| (k - 1, k)));
        let mut sorted = stacked.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..300).collect::<Vec<_>>());
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
        let (sparse, _, coordinates) = grid_system(12, 9);
        let err = sparse.factorise(100).unwrap_err();
        assert!(matches!(err, SparseError::TooLarge { limit: 100, entries } if entries > 100), "{err}");
        assert_eq!(
            sparse.factorise_at(usize::MAX, &coordinates[1..]).unwrap_err(),
            SparseError::Coordinates { given: coordinates.len() - 1, unknowns: coordinates.len() }
        );
        let mut out = SymmetricSparse::new(2);
        out.add(2, 0, 1.0);
        assert_eq!(
            out.solve(&[0.0; 2], usize::MAX).unwrap_err(),
            SparseError::OutOfRange { row: 2, column: 0, unknowns: 2 }
        );
    }
}
