//! Minimum s–t cut by the Boykov–Kolmogorov max-flow algorithm (Boykov & Kolmogorov, "An
//! experimental comparison of min-cut/max-flow algorithms for energy minimization in vision",
//! PAMI 2004): two search trees grown from the source and the sink, augmentation along the
//! paths where they meet, adoption of the orphans an augmentation leaves, with the paper's
//! distance/timestamp heuristic (§3.3 of Kolmogorov's implementation notes) for choosing
//! parents.
//!
//! Capacities are integers (exact arithmetic: the same cut whatever the order of
//! augmentations). Each node has a terminal capacity: positive = residual from the source,
//! negative = residual to the sink (a node's two terminal arcs are netted on entry, which adds
//! `min(c_s, c_t)` to the flow).

use std::collections::VecDeque;

/// Parent marker: the node hangs directly from its terminal.
const TERMINAL: u32 = u32::MAX - 1;
/// Parent marker: the node lost its parent and waits for adoption.
const ORPHAN: u32 = u32::MAX - 2;
/// Parent marker: the node is in no tree.
const FREE: u32 = u32::MAX;

/// A graph of `n` nodes with arcs in pairs (arc `a` and its reverse `a ^ 1`).
#[derive(Debug, Clone, Default)]
pub(crate) struct MaxFlow {
    /// First outgoing arc of each node (`FREE` = none).
    first: Vec<u32>,
    /// Head node of each arc.
    head: Vec<u32>,
    /// Next outgoing arc of the same tail (`FREE` = none).
    next: Vec<u32>,
    /// Residual capacity of each arc.
    cap: Vec<i64>,
    /// Net terminal residual: > 0 from the source, < 0 to the sink.
    terminal: Vec<i64>,
    /// Flow pushed so far (terminal netting included).
    flow: i64,
    /// Per node: the arc to its parent, or a marker.
    parent: Vec<u32>,
    /// Per node: in the sink tree (else source tree; meaningless when free).
    sink: Vec<bool>,
    /// Per node: the time its distance to the terminal was last checked.
    stamp: Vec<u32>,
    /// Per node: distance to its terminal along parents (valid at `stamp`).
    dist: Vec<u32>,
}

impl MaxFlow {
    /// A graph of `n` nodes without arcs.
    pub fn new(n: usize) -> Self {
        Self {
            first: vec![FREE; n],
            terminal: vec![0; n],
            ..Self::default()
        }
    }

    /// Adds the arc pair `p → q` (capacity `cap_pq`) and `q → p` (`cap_qp`); capacities ≥ 0.
    pub fn add_edge(&mut self, p: usize, q: usize, cap_pq: i64, cap_qp: i64) {
        debug_assert!(cap_pq >= 0 && cap_qp >= 0 && p != q);
        for (tail, hd, c) in [(p, q, cap_pq), (q, p, cap_qp)] {
            let a = self.head.len() as u32;
            self.head.push(hd as u32);
            self.cap.push(c);
            self.next.push(self.first[tail]);
            self.first[tail] = a;
        }
    }

    /// Adds capacity `from_source` on the arc source → `p` and `to_sink` on `p` → sink (≥ 0).
    pub fn add_terminal(&mut self, p: usize, from_source: i64, to_sink: i64) {
        debug_assert!(from_source >= 0 && to_sink >= 0);
        let (mut s, mut t) = (from_source, to_sink);
        let old = self.terminal[p];
        if old > 0 {
            s += old;
        } else {
            t -= old;
        }
        self.flow += s.min(t);
        self.terminal[p] = s - t;
    }

    /// Outgoing arcs of `p`.
    fn arcs(&self, p: usize) -> impl Iterator<Item = usize> + '_ {
        let mut a = self.first[p];
        std::iter::from_fn(move || {
            (a != FREE).then(|| {
                let cur = a as usize;
                a = self.next[cur];
                cur
            })
        })
    }

    /// Residual capacity of the arc that carries flow away from the root of `p`'s tree
    /// through arc `a` (out of `p`): `a` itself in the source tree, its reverse in the sink
    /// tree.
    fn outward(&self, sink: bool, a: usize) -> i64 {
        if sink { self.cap[a ^ 1] } else { self.cap[a] }
    }

    /// Computes the maximum flow; returns it. Afterwards [`MaxFlow::source_side`] tells each
    /// node's side of a minimum cut.
    pub fn solve(&mut self) -> i64 {
        let n = self.first.len();
        self.parent = vec![FREE; n];
        self.sink = vec![false; n];
        self.stamp = vec![0; n];
        self.dist = vec![0; n];
        // Every node with terminal residual starts in its terminal's tree, active.
        let mut active: VecDeque<u32> = VecDeque::new();
        let queued_init: Vec<bool> = self.terminal.iter().map(|t| *t != 0).collect();
        for (p, _) in queued_init.iter().enumerate().filter(|(_, q)| **q) {
            self.parent[p] = TERMINAL;
            self.sink[p] = self.terminal[p] < 0;
            self.dist[p] = 1;
            active.push_back(p as u32);
        }
        let mut queued = queued_init;
        let mut time = 0u32;
        let mut orphans: VecDeque<u32> = VecDeque::new();
        let mut current: Option<usize> = None;
        loop {
            // Growth: find an arc from the source tree to the sink tree.
            let i = match current.filter(|&c| self.parent[c] != FREE) {
                Some(c) => c,
                None => {
                    let mut pick = None;
                    while let Some(c) = active.pop_front() {
                        let c = c as usize;
                        queued[c] = false;
                        if self.parent[c] != FREE {
                            pick = Some(c);
                            break;
                        }
                    }
                    match pick {
                        Some(c) => c,
                        None => break,
                    }
                }
            };
            current = None;
            let in_sink = self.sink[i];
            let mut bridge = None;
            let arcs: Vec<usize> = self.arcs(i).collect();
            for a in arcs {
                if self.outward(in_sink, a) == 0 {
                    continue;
                }
                let j = self.head[a] as usize;
                if self.parent[j] == FREE {
                    self.sink[j] = in_sink;
                    self.parent[j] = (a ^ 1) as u32;
                    self.stamp[j] = self.stamp[i];
                    self.dist[j] = self.dist[i] + 1;
                    if !queued[j] {
                        queued[j] = true;
                        active.push_back(j as u32);
                    }
                } else if self.sink[j] != in_sink {
                    // The arc in the source → sink direction.
                    bridge = Some(if in_sink { a ^ 1 } else { a });
                    break;
                } else if self.stamp[j] <= self.stamp[i] && self.dist[j] > self.dist[i] {
                    self.parent[j] = (a ^ 1) as u32;
                    self.stamp[j] = self.stamp[i];
                    self.dist[j] = self.dist[i] + 1;
                }
            }
            let Some(bridge) = bridge else {
                continue;
            };
            // `i` may still grow once the orphans are adopted.
            current = Some(i);
            if !queued[i] {
                queued[i] = true;
                active.push_front(i as u32);
            }
            time += 1;
            self.augment(bridge, &mut orphans);
            while let Some(o) = orphans.pop_front() {
                self.adopt(o as usize, time, &mut orphans, &mut active, &mut queued);
            }
        }
        self.flow
    }

    /// Pushes the bottleneck along the path through `bridge` (source tree → sink tree);
    /// nodes whose parent arc saturates become orphans.
    fn augment(&mut self, bridge: usize, orphans: &mut VecDeque<u32>) {
        let s = self.head[bridge ^ 1] as usize;
        let t = self.head[bridge] as usize;
        let mut b = self.cap[bridge];
        let mut k = s;
        while self.parent[k] != TERMINAL {
            let a = self.parent[k] as usize;
            b = b.min(self.cap[a ^ 1]);
            k = self.head[a] as usize;
        }
        b = b.min(self.terminal[k]);
        let mut k = t;
        while self.parent[k] != TERMINAL {
            let a = self.parent[k] as usize;
            b = b.min(self.cap[a]);
            k = self.head[a] as usize;
        }
        b = b.min(-self.terminal[k]);

        self.cap[bridge] -= b;
        self.cap[bridge ^ 1] += b;
        let mut k = s;
        while self.parent[k] != TERMINAL {
            let a = self.parent[k] as usize;
            self.cap[a] += b;
            self.cap[a ^ 1] -= b;
            if self.cap[a ^ 1] == 0 {
                self.parent[k] = ORPHAN;
                orphans.push_back(k as u32);
            }
            k = self.head[a] as usize;
        }
        self.terminal[k] -= b;
        if self.terminal[k] == 0 {
            self.parent[k] = ORPHAN;
            orphans.push_back(k as u32);
        }
        let mut k = t;
        while self.parent[k] != TERMINAL {
            let a = self.parent[k] as usize;
            self.cap[a ^ 1] += b;
            self.cap[a] -= b;
            if self.cap[a] == 0 {
                self.parent[k] = ORPHAN;
                orphans.push_back(k as u32);
            }
            k = self.head[a] as usize;
        }
        self.terminal[k] += b;
        if self.terminal[k] == 0 {
            self.parent[k] = ORPHAN;
            orphans.push_back(k as u32);
        }
        self.flow += b;
    }

    /// Distance from `j` to its tree's terminal along parents, stamping the path at `time`;
    /// `None` if the path ends at an orphan.
    fn origin_distance(&mut self, j: usize, time: u32) -> Option<u32> {
        let mut d = 0u32;
        let mut k = j;
        loop {
            if self.stamp[k] == time {
                d += self.dist[k];
                break;
            }
            let a = self.parent[k];
            d += 1;
            if a == TERMINAL {
                self.stamp[k] = time;
                self.dist[k] = 1;
                break;
            }
            if a == ORPHAN || a == FREE {
                return None;
            }
            k = self.head[a as usize] as usize;
        }
        // Stamp the path with its distances.
        let mut k = j;
        let mut dk = d;
        while self.stamp[k] != time {
            self.stamp[k] = time;
            self.dist[k] = dk;
            dk -= 1;
            k = self.head[self.parent[k] as usize] as usize;
        }
        Some(d)
    }

    /// Finds orphan `i` a new parent in its tree, or frees it (its children become orphans,
    /// its neighbours that could reach it become active).
    fn adopt(
        &mut self,
        i: usize,
        time: u32,
        orphans: &mut VecDeque<u32>,
        active: &mut VecDeque<u32>,
        queued: &mut [bool],
    ) {
        let in_sink = self.sink[i];
        let mut best: Option<(u32, usize)> = None;
        let arcs: Vec<usize> = self.arcs(i).collect();
        for &a in &arcs {
            // Residual from the neighbour j towards i, seen from the root of i's tree.
            if self.outward(in_sink, a ^ 1) == 0 {
                continue;
            }
            let j = self.head[a] as usize;
            if self.parent[j] == FREE || self.sink[j] != in_sink {
                continue;
            }
            if let Some(d) = self.origin_distance(j, time)
                && best.is_none_or(|(bd, _)| d < bd)
            {
                best = Some((d, a));
            }
        }
        if let Some((d, a)) = best {
            self.parent[i] = a as u32;
            self.stamp[i] = time;
            self.dist[i] = d + 1;
            return;
        }
        for &a in &arcs {
            let j = self.head[a] as usize;
            if self.parent[j] == FREE || self.sink[j] != in_sink {
                continue;
            }
            if self.outward(in_sink, a ^ 1) > 0 && !queued[j] {
                queued[j] = true;
                active.push_back(j as u32);
            }
            let pj = self.parent[j];
            if pj != TERMINAL && pj != ORPHAN && self.head[pj as usize] as usize == i {
                self.parent[j] = ORPHAN;
                orphans.push_back(j as u32);
            }
        }
        self.parent[i] = FREE;
    }

    /// Whether node `p` is on the source side of the minimum cut found by
    /// [`MaxFlow::solve`] (the nodes the source still reaches in the residual graph).
    pub fn source_side(&self, p: usize) -> bool {
        self.parent[p] != FREE && !self.sink[p]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tiny deterministic generator (64-bit LCG, high bits).
    struct Lcg(u64);
    impl Lcg {
        fn below(&mut self, n: u64) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (self.0 >> 33) % n
        }
    }

    struct Case {
        n: usize,
        edges: Vec<(usize, usize, i64, i64)>,
        terminals: Vec<(i64, i64)>,
    }

    /// Cost of the cut that puts the nodes with bit set in `mask` on the source side.
    fn cut_cost(c: &Case, mask: u32) -> i64 {
        let src = |p: usize| mask >> p & 1 == 1;
        let mut cost = 0;
        for (p, &(s, t)) in c.terminals.iter().enumerate() {
            cost += if src(p) { t } else { s };
        }
        for &(p, q, pq, qp) in &c.edges {
            if src(p) && !src(q) {
                cost += pq;
            }
            if src(q) && !src(p) {
                cost += qp;
            }
        }
        cost
    }

    fn random_case(rng: &mut Lcg, n: usize) -> Case {
        let mut edges = Vec::new();
        for p in 0..n {
            for q in p + 1..n {
                if rng.below(3) == 0 {
                    edges.push((p, q, rng.below(10) as i64, rng.below(10) as i64));
                }
            }
        }
        let terminals = (0..n)
            .map(|_| (rng.below(12) as i64, rng.below(12) as i64))
            .collect();
        Case {
            n,
            edges,
            terminals,
        }
    }

    fn solve(c: &Case) -> (i64, MaxFlow) {
        let mut g = MaxFlow::new(c.n);
        for &(p, q, a, b) in &c.edges {
            g.add_edge(p, q, a, b);
        }
        for (p, &(s, t)) in c.terminals.iter().enumerate() {
            g.add_terminal(p, s, t);
        }
        (g.solve(), g)
    }

    #[test]
    fn flow_equals_the_brute_force_minimum_cut() {
        let mut rng = Lcg(7);
        for trial in 0..400 {
            let c = random_case(&mut rng, 2 + trial % 9);
            let best = (0..1u32 << c.n).map(|m| cut_cost(&c, m)).min().unwrap();
            let (flow, g) = solve(&c);
            assert_eq!(flow, best, "trial {trial}: flow vs brute-force minimum cut");
            let mask = (0..c.n)
                .filter(|&p| g.source_side(p))
                .fold(0u32, |m, p| m | 1 << p);
            assert_eq!(cut_cost(&c, mask), best, "trial {trial}: the labels' cut");
        }
    }

    #[test]
    fn grid_graphs_match_brute_force() {
        // 3x4 4-connected grids with symmetric weights, as the matte builds them.
        let mut rng = Lcg(11);
        for trial in 0..100 {
            let (w, h) = (4, 3);
            let mut edges = Vec::new();
            for y in 0..h {
                for x in 0..w {
                    let p = y * w + x;
                    if x + 1 < w {
                        let c = rng.below(6) as i64;
                        edges.push((p, p + 1, c, c));
                    }
                    if y + 1 < h {
                        let c = rng.below(6) as i64;
                        edges.push((p, p + w, c, c));
                    }
                }
            }
            let terminals = (0..w * h)
                .map(|_| (rng.below(10) as i64, rng.below(10) as i64))
                .collect();
            let c = Case {
                n: w * h,
                edges,
                terminals,
            };
            let best = (0..1u32 << c.n).map(|m| cut_cost(&c, m)).min().unwrap();
            assert_eq!(solve(&c).0, best, "trial {trial}");
        }
    }

    #[test]
    fn trivial_graphs() {
        let mut g = MaxFlow::new(0);
        assert_eq!(g.solve(), 0);
        let mut g = MaxFlow::new(1);
        g.add_terminal(0, 5, 3);
        assert_eq!(g.solve(), 3);
        assert!(g.source_side(0));
        let mut g = MaxFlow::new(2);
        g.add_terminal(0, 4, 0);
        g.add_terminal(1, 0, 9);
        g.add_edge(0, 1, 2, 0);
        assert_eq!(g.solve(), 2);
        assert!(g.source_side(0) && !g.source_side(1));
    }
}
