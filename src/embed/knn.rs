//! k-nearest neighbours of 3D points with a k-d tree: O(n log n) build, queries in parallel.
//!
//! Used by the Trio-Experts for the neighbourhood 𝒩_k(i) in position space. Results are exact
//! and deterministic: neighbours are ordered by (squared distance, index), the query point
//! itself is excluded, and ties at equal distance go to the smaller index — so the answer equals
//! a brute-force sort, which the tests check.

use rayon::prelude::*;

/// Points per leaf.
const LEAF: usize = 12;

#[derive(Clone, Copy, Debug)]
enum Node {
    /// `order[start..end]` are the leaf's points.
    Leaf { start: u32, end: u32 },
    /// Points of `left` have coordinate ≤ `value` on `axis`, those of `right` ≥ `value`.
    Split {
        axis: u8,
        value: f32,
        left: u32,
        right: u32,
    },
}

/// A k-d tree (median split on the widest axis) holding a copy of the points in tree order.
pub struct KdTree {
    /// Points in tree order: each leaf's points are contiguous.
    pts: Vec<[f32; 3]>,
    /// `order[s]`: the caller's index of `pts[s]`.
    order: Vec<u32>,
    nodes: Vec<Node>,
}

impl KdTree {
    /// Builds the tree. Points must be finite.
    pub fn new(points: &[[f32; 3]]) -> Self {
        assert!(
            points.len() < u32::MAX as usize,
            "too many points for a k-d tree"
        );
        let mut order: Vec<u32> = (0..points.len() as u32).collect();
        let mut nodes = Vec::with_capacity(2 * points.len() / LEAF + 1);
        if !points.is_empty() {
            build(points, &mut order, 0, &mut nodes);
        }
        let pts = order.iter().map(|&i| points[i as usize]).collect();
        Self { pts, order, nodes }
    }

    /// The `k` nearest points to `q` other than index `exclude` (pass `u32::MAX` to exclude
    /// none), nearest first, as (squared distance, index); fewer when there are fewer points.
    pub fn nearest(&self, q: [f32; 3], k: usize, exclude: u32) -> Vec<(f32, u32)> {
        let mut best = Best::new(k);
        if k > 0 && !self.nodes.is_empty() {
            self.search(0, q, exclude, 0.0, [0.0; 3], &mut best);
        }
        best.items
    }

    /// Visits `node`, whose cell is at squared distance ≥ `rd` from `q`; `off[a]` is the
    /// per-axis offset from `q` to the cell that makes up `rd` (Arya & Mount's incremental
    /// distance), so every point of the cell is at least `rd` away.
    fn search(
        &self,
        node: usize,
        q: [f32; 3],
        exclude: u32,
        rd: f32,
        off: [f32; 3],
        best: &mut Best,
    ) {
        match self.nodes[node] {
            Node::Leaf { start, end } => {
                for s in start as usize..end as usize {
                    let j = self.order[s];
                    if j != exclude {
                        best.offer(dist2(q, self.pts[s]), j);
                    }
                }
            }
            Node::Split {
                axis,
                value,
                left,
                right,
            } => {
                let a = axis as usize;
                let d = q[a] - value;
                let (near, far) = if d < 0.0 {
                    (left, right)
                } else {
                    (right, left)
                };
                self.search(near as usize, q, exclude, rd, off, best);
                // Points beyond the plane are at least |d| away along `axis`. Replacing this
                // axis' part of the bound keeps it a lower bound; the far cell can hold a
                // better or tied point only if the bound is ≤ the current k-th distance. The
                // 1e-5 slack covers the rounding of the incremental sum, so ties at exactly
                // the k-th distance are never missed (the answer stays brute-force exact).
                let far_rd = rd - off[a] * off[a] + d * d;
                if best.wants(far_rd * (1.0 - 1e-5)) {
                    let mut o = off;
                    o[a] = d;
                    self.search(far as usize, q, exclude, far_rd, o, best);
                }
            }
        }
    }
}

fn build(points: &[[f32; 3]], order: &mut [u32], offset: u32, nodes: &mut Vec<Node>) -> u32 {
    let id = nodes.len() as u32;
    let n = order.len();
    if n <= LEAF {
        nodes.push(Node::Leaf {
            start: offset,
            end: offset + n as u32,
        });
        return id;
    }
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for &i in order.iter() {
        let p = points[i as usize];
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let axis = (0..3)
        .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])))
        .unwrap_or(0);
    let mid = n / 2;
    order.select_nth_unstable_by(mid, |&a, &b| {
        points[a as usize][axis].total_cmp(&points[b as usize][axis])
    });
    let value = points[order[mid] as usize][axis];
    nodes.push(Node::Leaf { start: 0, end: 0 }); // placeholder, filled below
    let (l, r) = order.split_at_mut(mid);
    let left = build(points, l, offset, nodes);
    let right = build(points, r, offset + mid as u32, nodes);
    nodes[id as usize] = Node::Split {
        axis: axis as u8,
        value,
        left,
        right,
    };
    id
}

#[inline(always)]
fn dist2(a: [f32; 3], b: [f32; 3]) -> f32 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
}

/// The best `k` candidates so far, sorted by (distance², index).
struct Best {
    k: usize,
    items: Vec<(f32, u32)>,
}

impl Best {
    fn new(k: usize) -> Self {
        Self {
            k,
            items: Vec::with_capacity(k + 1),
        }
    }

    #[inline(always)]
    fn wants(&self, d2: f32) -> bool {
        self.items.len() < self.k || d2 <= self.items[self.k - 1].0
    }

    #[inline(always)]
    fn offer(&mut self, d2: f32, j: u32) {
        let key = (d2, j);
        if self.items.len() == self.k {
            let last = self.items[self.k - 1];
            if !less(key, last) {
                return;
            }
            self.items.pop();
        }
        let pos = self.items.partition_point(|&x| less(x, key));
        self.items.insert(pos, key);
    }
}

#[inline(always)]
fn less(a: (f32, u32), b: (f32, u32)) -> bool {
    a.0 < b.0 || (a.0 == b.0 && a.1 < b.1)
}

/// The k nearest neighbours of every point among the others.
#[derive(Clone, Debug, PartialEq)]
pub struct Knn {
    /// Neighbours per point (`min(k, n − 1)`).
    pub k: usize,
    /// `idx[i*k .. (i+1)*k]`: neighbours of point i, nearest first.
    pub idx: Vec<u32>,
    /// Squared distances matching `idx`.
    pub dist2: Vec<f32>,
}

impl Knn {
    /// Neighbour indices of point `i`.
    pub fn of(&self, i: usize) -> &[u32] {
        &self.idx[i * self.k..(i + 1) * self.k]
    }

    /// Squared distances of the neighbours of point `i`.
    pub fn dist2_of(&self, i: usize) -> &[f32] {
        &self.dist2[i * self.k..(i + 1) * self.k]
    }
}

/// The `k` nearest other points of every point (k-d tree, queries in parallel).
pub fn knn(points: &[[f32; 3]], k: usize) -> Knn {
    let n = points.len();
    let k = k.min(n.saturating_sub(1));
    let mut idx = vec![0u32; n * k];
    let mut dist2 = vec![0f32; n * k];
    if k == 0 {
        return Knn { k, idx, dist2 };
    }
    let tree = KdTree::new(points);
    // Query in tree order (neighbouring queries touch the same cells), then scatter.
    let found: Vec<(f32, u32)> = (0..n)
        .into_par_iter()
        .with_min_len(256)
        .flat_map_iter(|s| {
            let nb = tree.nearest(tree.pts[s], k, tree.order[s]);
            debug_assert_eq!(nb.len(), k);
            nb.into_iter()
        })
        .collect();
    for (s, chunk) in found.chunks_exact(k).enumerate() {
        let i = tree.order[s] as usize;
        for (slot, &(d, j)) in chunk.iter().enumerate() {
            idx[i * k + slot] = j;
            dist2[i * k + slot] = d;
        }
    }
    Knn { k, idx, dist2 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::Rng;

    fn brute(points: &[[f32; 3]], k: usize) -> Knn {
        let n = points.len();
        let k = k.min(n.saturating_sub(1));
        let mut idx = Vec::new();
        let mut d2s = Vec::new();
        for i in 0..n {
            let mut all: Vec<(f32, u32)> = (0..n)
                .filter(|&j| j != i)
                .map(|j| (dist2(points[i], points[j]), j as u32))
                .collect();
            all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            for &(d, j) in &all[..k] {
                idx.push(j);
                d2s.push(d);
            }
        }
        Knn { k, idx, dist2: d2s }
    }

    #[test]
    fn kd_tree_matches_brute_force() {
        let mut rng = Rng::new(7);
        // Uniform points, a dense cluster, exact duplicates, points on a grid (many ties) and
        // far outliers: every way a k-d tree can go wrong.
        let mut pts: Vec<[f32; 3]> = (0..1500)
            .map(|_| {
                [
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                ]
            })
            .collect();
        pts.extend((0..600).map(|_| [rng.normal() * 1e-3, rng.normal() * 1e-3, 0.5]));
        let dups: Vec<[f32; 3]> = pts[..80].to_vec();
        pts.extend(dups);
        for x in 0..6 {
            for y in 0..6 {
                for z in 0..6 {
                    pts.push([x as f32 * 0.25, y as f32 * 0.25, z as f32 * 0.25 + 3.0]);
                }
            }
        }
        pts.extend([[100.0, 0.0, 0.0], [-50.0, 20.0, 1.0], [0.0, 0.0, 1e4]]);
        for k in [1, 5, 16] {
            assert_eq!(knn(&pts, k), brute(&pts, k), "k = {k}");
        }
        // Queries at arbitrary positions (not members) agree too.
        let tree = KdTree::new(&pts);
        for _ in 0..200 {
            let q = [
                rng.range(-2.0, 2.0),
                rng.range(-2.0, 2.0),
                rng.range(-1.0, 4.5),
            ];
            let mut all: Vec<(f32, u32)> = pts
                .iter()
                .enumerate()
                .map(|(j, &p)| (dist2(q, p), j as u32))
                .collect();
            all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            assert_eq!(tree.nearest(q, 9, u32::MAX), all[..9].to_vec());
        }
    }

    #[test]
    fn tiny_inputs() {
        assert_eq!(knn(&[], 4).idx.len(), 0);
        let one = knn(&[[1.0, 2.0, 3.0]], 4);
        assert_eq!((one.k, one.idx.len()), (0, 0));
        let two = knn(&[[0.0; 3], [3.0, 4.0, 0.0]], 4);
        assert_eq!(two.k, 1);
        assert_eq!(two.idx, vec![1, 0]);
        assert_eq!(two.dist2, vec![25.0, 25.0]);
    }

    #[test]
    #[ignore = "timing: cargo test --lib knn_million -- --ignored --nocapture"]
    fn knn_million() {
        let pts: Vec<[f32; 3]> = crate::scene::synthetic::object_scene(1_000_000, 0, 5).means;
        let t = std::time::Instant::now();
        let r = knn(&pts, 16);
        eprintln!("1M points, k = 16: {:.2} s", t.elapsed().as_secs_f64());
        assert_eq!(r.idx.len(), 16_000_000);
    }
}
