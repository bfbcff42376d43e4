//! Felzenszwalb & Huttenlocher (2004), "Efficient graph-based image segmentation": edges sorted
//! by weight (O(m log m)), then merged in that order with union–find whenever the edge is no
//! heavier than both components' internal difference (largest MST edge) plus `k / |C|`.

/// Disjoint sets with union by size and path halving, carrying each component's internal
/// difference.
#[derive(Clone, Debug)]
pub struct UnionFind {
    parent: Vec<u32>,
    size: Vec<u32>,
    internal: Vec<f32>,
}

impl UnionFind {
    pub fn new(n: usize) -> Self {
        Self { parent: (0..n as u32).collect(), size: vec![1; n], internal: vec![0.0; n] }
    }

    pub fn find(&mut self, mut x: u32) -> u32 {
        while self.parent[x as usize] != x {
            let p = self.parent[x as usize];
            self.parent[x as usize] = self.parent[p as usize];
            x = p;
        }
        x
    }

    /// Size of the component whose root is `root`.
    pub fn size(&self, root: u32) -> u32 {
        self.size[root as usize]
    }

    /// Joins the components of `a` and `b` over an edge of weight 0. Felzenszwalb–Huttenlocher
    /// takes every such edge (its threshold `Int(C) + k/|C|` is positive for k > 0), in whatever
    /// order, so they can be joined while the graph is built and need not be sorted
    /// ([`felzenszwalb_huttenlocher_from`]).
    #[inline]
    pub fn join_weightless(&mut self, a: u32, b: u32) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            self.union(ra, rb, 0.0);
        }
    }

    fn union(&mut self, a: u32, b: u32, w: f32) {
        let (big, small) = if self.size[a as usize] >= self.size[b as usize] { (a, b) } else { (b, a) };
        self.parent[small as usize] = big;
        self.size[big as usize] += self.size[small as usize];
        self.internal[big as usize] = w.max(self.internal[big as usize]).max(self.internal[small as usize]);
    }
}

/// Segments a graph of `n` nodes given its weighted edges `(w, a, b)`. Afterwards, as in the
/// paper's post-processing, components smaller than `min_size` are joined to a neighbour over
/// edges no heavier than `merge_max` (lightest first): isolated noisy pixels of a surface rejoin
/// it, while clutter (whose edges are all heavy or cut) stays small and can be removed.
pub fn felzenszwalb_huttenlocher(
    n: usize,
    edges: Vec<(f32, u32, u32)>,
    k: f64,
    min_size: u32,
    merge_max: f32,
) -> UnionFind {
    felzenszwalb_huttenlocher_from(UnionFind::new(n), edges, k, min_size, merge_max)
}

/// [`felzenszwalb_huttenlocher`] over a graph whose edges of weight 0 were already joined in `uf`
/// ([`UnionFind::join_weightless`], which requires k > 0); `edges` holds the others. The result
/// is the same as with all edges given, and sorting only the weighted edges is cheaper.
pub fn felzenszwalb_huttenlocher_from(
    mut uf: UnionFind,
    mut edges: Vec<(f32, u32, u32)>,
    k: f64,
    min_size: u32,
    merge_max: f32,
) -> UnionFind {
    // Weights are finite and non-negative: their bit patterns sort like the numbers.
    edges.sort_unstable_by_key(|e| e.0.to_bits());
    let k = k as f32;
    for &(w, a, b) in &edges {
        let (ra, rb) = (uf.find(a), uf.find(b));
        if ra == rb {
            continue;
        }
        let ta = uf.internal[ra as usize] + k / uf.size[ra as usize] as f32;
        let tb = uf.internal[rb as usize] + k / uf.size[rb as usize] as f32;
        if w <= ta.min(tb) {
            uf.union(ra, rb, w);
        }
    }
    for &(w, a, b) in &edges {
        if w > merge_max {
            break;
        }
        let (ra, rb) = (uf.find(a), uf.find(b));
        if ra != rb && uf.size[ra as usize].min(uf.size[rb as usize]) < min_size {
            uf.union(ra, rb, w);
        }
    }
    uf
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A chain of two plateaus joined by one heavy edge stays two components; with a huge k
    /// everything merges.
    #[test]
    fn internal_difference_rule() {
        let mut edges = vec![];
        for i in 0..9u32 {
            edges.push((if i == 4 { 5.0 } else { 0.1 + 0.01 * i as f32 }, i, i + 1));
        }
        let mut uf = felzenszwalb_huttenlocher(10, edges.clone(), 1.0, 0, 0.0);
        assert_eq!(uf.find(0), uf.find(4));
        assert_eq!(uf.find(5), uf.find(9));
        assert_ne!(uf.find(4), uf.find(5));
        let mut uf = felzenszwalb_huttenlocher(10, edges.clone(), 100.0, 0, 0.0);
        assert_eq!(uf.find(0), uf.find(9));
        // A singleton behind a light edge joins its neighbour in the post-processing, not behind a
        // heavy one.
        let mut single = edges.clone();
        single[0].0 = 0.9;
        let mut uf = felzenszwalb_huttenlocher(10, single.clone(), 0.01, 3, 1.0);
        assert_eq!(uf.find(0), uf.find(1));
        single[0].0 = 2.0;
        let mut uf = felzenszwalb_huttenlocher(10, single, 0.01, 3, 1.0);
        assert_ne!(uf.find(0), uf.find(1));
        let mut uf = felzenszwalb_huttenlocher(10, edges, 100.0, 0, 0.0);
        assert_eq!(uf.find(0), uf.find(9));
        let root = uf.find(0);
        assert_eq!(uf.size(root), 10);
    }

    /// Joining the weight-0 edges first gives the partition of the full sort, on a random graph
    /// with many zero weights.
    #[test]
    fn weightless_edges_joined_first_give_the_same_partition() {
        let mut seed = 11u64;
        let mut rand = move |m: u64| {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 33) % m
        };
        let n = 2000;
        for trial in 0..20 {
            let edges: Vec<(f32, u32, u32)> = (0..3 * n)
                .map(|_| {
                    let w = if rand(3) == 0 { 0.0 } else { rand(400) as f32 * 0.01 + 0.001 * rand(7) as f32 };
                    (w, rand(n as u64) as u32, rand(n as u64) as u32)
                })
                .collect();
            let k = 0.5 + trial as f64 * 0.3;
            let mut full = felzenszwalb_huttenlocher(n, edges.clone(), k, 5, 1.0);
            let mut uf = UnionFind::new(n);
            let mut weighted = vec![];
            for &(w, a, b) in &edges {
                if w == 0.0 {
                    uf.join_weightless(a, b);
                } else {
                    weighted.push((w, a, b));
                }
            }
            let mut split = felzenszwalb_huttenlocher_from(uf, weighted, k, 5, 1.0);
            let mut components = 0;
            for a in 0..n as u32 {
                components += (full.find(a) == a) as u32;
                for b in [(a * 7 + 3) % n as u32, (a + 1) % n as u32] {
                    assert_eq!(full.find(a) == full.find(b), split.find(a) == split.find(b), "trial {trial}");
                }
            }
            assert!(components > 1 && components < n as u32 / 2, "trial {trial}: {components} components");
        }
    }
}
