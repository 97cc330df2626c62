//! Minimum s–t cuts: the Boykov–Kolmogorov max-flow algorithm ("An Experimental Comparison of
//! Min-Cut/Max-Flow Algorithms for Energy Minimization in Vision", PAMI 2004) and the binary
//! energies it minimises ([`BinaryEnergy`]: unary terms, submodular pairwise terms, forbidden
//! pairs), as graph-cut stereo needs them.
//!
//! Two search trees, one rooted at the source and one at the sink, grow along non-saturated arcs
//! until they touch; the path found is augmented, the nodes cut off by saturated arcs become
//! orphans and are re-attached (adopted) to their tree where possible, so the trees are reused
//! from one augmentation to the next instead of being searched again. Nodes of the source tree
//! carry a time stamp and their distance to the terminal, so adoption prefers short paths.
//!
//! A [`Graph`] keeps its storage between problems ([`Graph::reset`]): an α-expansion builds a new
//! graph of about the same size for every label.
//!
//! [`reference_max_flow`] is the plain Edmonds–Karp algorithm (breadth-first augmenting paths)
//! the tests check this one against.

use std::collections::VecDeque;

/// Capacity and flow values of the API (flows are summed in `i64`).
pub type Capacity = i64;

/// Residual capacities as stored: an arc and its reverse always sum to what was added, so a
/// pair whose capacities fit [`INFINITE_CAPACITY`] never overflows.
type Residual = i32;

/// A capacity no cut may pay (forbidden labellings); also the largest capacity an arc or a
/// terminal may have.
pub const INFINITE_CAPACITY: Capacity = 1 << 30;

/// No parent (a free node).
const NONE: u32 = u32::MAX;
/// Parent of a node attached directly to its terminal.
const TERMINAL: u32 = u32::MAX - 1;
/// Parent of an orphan (cut off from its tree, waiting for adoption).
const ORPHAN: u32 = u32::MAX - 2;
/// Distance of a node not (yet) known to reach its terminal.
const INFINITE_DISTANCE: u32 = u32::MAX;

/// Which side of the minimum cut a node lies on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Segment {
    /// Reachable from the source in the residual graph (or not connected to the sink).
    Source,
    /// Reaches the sink in the residual graph.
    Sink,
}

#[derive(Debug, Clone, Copy)]
struct Node {
    /// Arc towards the parent in the search tree, or [`TERMINAL`], [`ORPHAN`], [`NONE`] (free).
    parent: u32,
    /// Time stamp of `dist`.
    time: u32,
    /// Distance to the terminal along parents (valid when `time` is current).
    dist: u32,
    /// Residual terminal capacity: > 0 from the source, < 0 to the sink.
    terminal: Residual,
    /// In the sink tree (else the source tree, when it has a parent).
    in_sink_tree: bool,
    /// Queued as active.
    queued: bool,
}

#[derive(Debug, Clone, Copy)]
struct Arc {
    /// Node the arc points to.
    head: u32,
    /// The reverse arc.
    sister: u32,
    /// Residual capacity.
    residual: Residual,
    /// Residual capacity of the reverse arc (a copy, kept in step, so that the searches read
    /// both directions from one place).
    reverse: Residual,
}

/// An edge as added, before the arcs are laid out.
#[derive(Debug, Clone, Copy)]
struct Edge {
    from: u32,
    to: u32,
    capacity: Residual,
    reverse: Residual,
}

/// A directed graph with source and sink capacities, cut by Boykov–Kolmogorov max-flow.
/// Edges are collected as added, then laid out once per [`Graph::max_flow`] with the arcs of
/// every node contiguous (each with its reverse arc), which keeps the searches in cache.
#[derive(Debug, Default, Clone)]
pub struct Graph {
    nodes: Vec<Node>,
    edges: Vec<Edge>,
    /// Arcs of node `i`: `arcs[first[i] as usize..first[i + 1] as usize]`.
    first: Vec<u32>,
    arcs: Vec<Arc>,
    /// Flow already forced through both terminal arcs of a node (`min(source, sink)` of each
    /// [`Graph::add_terminal_weights`]) plus the augmented flow.
    flow: Capacity,
    active: VecDeque<u32>,
    orphans: VecDeque<u32>,
    time: u32,
}

#[inline]
fn clamp(c: Capacity) -> Residual {
    c.clamp(-INFINITE_CAPACITY, INFINITE_CAPACITY) as Residual
}

impl Graph {
    /// An empty graph.
    pub fn new() -> Self {
        Self::default()
    }

    /// Removes every node and edge, keeping the storage.
    pub fn reset(&mut self) {
        self.nodes.clear();
        self.edges.clear();
        self.first.clear();
        self.arcs.clear();
        self.flow = 0;
        self.active.clear();
        self.orphans.clear();
        self.time = 0;
    }

    /// Reserves room for this many more nodes and edges.
    pub fn reserve(&mut self, nodes: usize, edges: usize) {
        self.nodes.reserve(nodes);
        self.edges.reserve(edges);
        // The laid-out arcs and node offsets too, once at their largest: grown by doubling over
        // the moves, each outgrown buffer stayed in the process (replay's allocator keeps freed
        // pages), and pages reserved but never written cost no memory.
        self.first.reserve(nodes + 1);
        self.arcs.reserve(2 * edges);
    }

    /// Adds a node without terminal capacities; returns its index.
    pub fn add_node(&mut self) -> u32 {
        self.nodes.push(Node {
            parent: NONE,
            time: 0,
            dist: 0,
            terminal: 0,
            in_sink_tree: false,
            queued: false,
        });
        (self.nodes.len() - 1) as u32
    }

    /// Adds capacities from the source to `node` and from `node` to the sink. Only their
    /// difference is kept as a terminal arc; the common part is flow that every cut pays.
    /// Negative capacities are allowed (they shift the flow by a constant). The difference must
    /// stay within ±[`INFINITE_CAPACITY`].
    pub fn add_terminal_weights(&mut self, node: u32, source: Capacity, sink: Capacity) {
        let current = Capacity::from(self.nodes[node as usize].terminal);
        let (mut source, mut sink) = (source, sink);
        if current > 0 {
            source += current;
        } else {
            sink -= current;
        }
        self.flow += source.min(sink);
        debug_assert!((source - sink).abs() <= INFINITE_CAPACITY);
        self.nodes[node as usize].terminal = clamp(source - sink);
    }

    /// Adds the arc `from → to` with capacity `capacity` and `to → from` with `reverse`
    /// (each at most [`INFINITE_CAPACITY`]).
    pub fn add_edge(&mut self, from: u32, to: u32, capacity: Capacity, reverse: Capacity) {
        debug_assert!(from != to && capacity >= 0 && reverse >= 0);
        self.edges.push(Edge {
            from,
            to,
            capacity: clamp(capacity),
            reverse: clamp(reverse),
        });
    }

    /// The side of the minimum cut of `node` (after [`Graph::max_flow`]). Nodes connected to
    /// neither terminal are on the source side.
    pub fn segment(&self, node: u32) -> Segment {
        let n = &self.nodes[node as usize];
        if n.parent != NONE && n.in_sink_tree {
            Segment::Sink
        } else {
            Segment::Source
        }
    }

    /// Lays the arcs out per node (a counting sort of the edges by tail).
    #[inline(never)]
    fn layout(&mut self) {
        let n = self.nodes.len();
        self.first.clear();
        self.first.resize(n + 1, 0);
        for e in &self.edges {
            self.first[e.from as usize + 1] += 1;
            self.first[e.to as usize + 1] += 1;
        }
        for i in 0..n {
            self.first[i + 1] += self.first[i];
        }
        self.arcs.clear();
        self.arcs.resize(
            2 * self.edges.len(),
            Arc {
                head: 0,
                sister: 0,
                residual: 0,
                reverse: 0,
            },
        );
        // `next[i]`: where node i's next arc goes (reuses `first` shifted by one slot).
        let mut next: Vec<u32> = self.first[..n].to_vec();
        for e in &self.edges {
            let a = next[e.from as usize];
            next[e.from as usize] += 1;
            let b = next[e.to as usize];
            next[e.to as usize] += 1;
            self.arcs[a as usize] = Arc {
                head: e.to,
                sister: b,
                residual: e.capacity,
                reverse: e.reverse,
            };
            self.arcs[b as usize] = Arc {
                head: e.from,
                sister: a,
                residual: e.reverse,
                reverse: e.capacity,
            };
        }
    }

    /// Computes the maximum flow (equal to the minimum cut's capacity, plus the constant flow of
    /// [`Graph::add_terminal_weights`]).
    pub fn max_flow(&mut self) -> Capacity {
        self.layout();
        self.push_direct_paths();
        self.init_trees();
        let mut current: Option<u32> = None;
        loop {
            let node = match current.take() {
                Some(i) if self.nodes[i as usize].parent != NONE => i,
                _ => match self.next_active() {
                    Some(i) => i,
                    None => break,
                },
            };
            let Some(middle) = self.grow(node) else {
                continue;
            };
            // Keep growing from the same node after the augmentation: it may have more arcs.
            current = Some(node);
            self.time = self.time.wrapping_add(1);
            self.augment(middle);
            self.adopt_orphans();
        }
        self.flow
    }

    #[inline(never)]
    /// Saturates the paths source → i → j → sink of one arc first, without any search (most of
    /// the flow of an α-expansion graph: each pixel's two variables joined by a forbidding arc).
    fn push_direct_paths(&mut self) {
        for i in 0..self.nodes.len() {
            if self.nodes[i].terminal <= 0 {
                continue;
            }
            for a in self.arc_range(i as u32) {
                let arc = self.arcs[a];
                let j = arc.head as usize;
                let (from_source, to_sink) = (self.nodes[i].terminal, -self.nodes[j].terminal);
                if to_sink <= 0 || arc.residual <= 0 {
                    continue;
                }
                let amount = from_source.min(to_sink).min(arc.residual);
                self.push(a as u32, amount);
                self.nodes[i].terminal -= amount;
                self.nodes[j].terminal += amount;
                self.flow += Capacity::from(amount);
                if self.nodes[i].terminal == 0 {
                    break;
                }
            }
        }
    }

    fn init_trees(&mut self) {
        self.active.clear();
        self.orphans.clear();
        self.time = 0;
        for i in 0..self.nodes.len() {
            let node = &mut self.nodes[i];
            node.time = 0;
            node.queued = false;
            if node.terminal != 0 {
                node.in_sink_tree = node.terminal < 0;
                node.parent = TERMINAL;
                node.dist = 1;
                node.queued = true;
                self.active.push_back(i as u32);
            } else {
                node.parent = NONE;
            }
        }
    }

    #[inline]
    fn activate(&mut self, node: u32) {
        let n = &mut self.nodes[node as usize];
        if !n.queued {
            n.queued = true;
            self.active.push_back(node);
        }
    }

    fn next_active(&mut self) -> Option<u32> {
        while let Some(i) = self.active.pop_front() {
            let n = &mut self.nodes[i as usize];
            n.queued = false;
            if n.parent != NONE {
                return Some(i);
            }
        }
        None
    }

    #[inline]
    fn arc_range(&self, node: u32) -> std::ops::Range<usize> {
        self.first[node as usize] as usize..self.first[node as usize + 1] as usize
    }

    /// Grows the tree of `node` by its neighbours; returns the arc (source side → sink side)
    /// where the trees meet.
    #[inline(never)]
    fn grow(&mut self, node: u32) -> Option<u32> {
        let (sink_tree, time, dist) = {
            let n = &self.nodes[node as usize];
            (n.in_sink_tree, n.time, n.dist)
        };
        for a in self.arc_range(node) {
            let arc = self.arcs[a];
            // Residual in the direction the tree grows: away from the source, towards the sink.
            let residual = if sink_tree { arc.reverse } else { arc.residual };
            if residual <= 0 {
                continue;
            }
            let j = arc.head as usize;
            let other = self.nodes[j];
            if other.parent == NONE {
                let n = &mut self.nodes[j];
                n.in_sink_tree = sink_tree;
                n.parent = arc.sister;
                n.time = time;
                n.dist = dist.saturating_add(1);
                self.activate(j as u32);
            } else if other.in_sink_tree != sink_tree {
                return Some(if sink_tree { arc.sister } else { a as u32 });
            } else if other.time <= time && other.dist > dist {
                // Shorter path to the terminal through `node`.
                let n = &mut self.nodes[j];
                n.parent = arc.sister;
                n.time = time;
                n.dist = dist.saturating_add(1);
            }
        }
        None
    }

    /// Cuts `node` off its tree. Orphans of an augmentation are processed before those their
    /// adoption frees (as Boykov and Kolmogorov's implementation does).
    #[inline]
    fn make_orphan(&mut self, node: u32, first: bool) {
        self.nodes[node as usize].parent = ORPHAN;
        if first {
            self.orphans.push_front(node);
        } else {
            self.orphans.push_back(node);
        }
    }

    /// Sends `amount` along arc `a` (updating both arcs of the pair and their copies).
    #[inline]
    fn push(&mut self, a: u32, amount: Residual) {
        let sister = {
            let arc = &mut self.arcs[a as usize];
            arc.residual -= amount;
            arc.reverse += amount;
            arc.sister
        };
        let back = &mut self.arcs[sister as usize];
        back.residual += amount;
        back.reverse -= amount;
    }

    /// Pushes the bottleneck along source → tail(middle) → head(middle) → sink.
    #[inline(never)]
    fn augment(&mut self, middle: u32) {
        let m = self.arcs[middle as usize];
        let tail = self.arcs[m.sister as usize].head;
        let mut bottleneck = m.residual;
        // Source side: the tail of `middle` up to the source.
        let mut i = tail;
        loop {
            let a = self.nodes[i as usize].parent;
            if a == TERMINAL {
                bottleneck = bottleneck.min(self.nodes[i as usize].terminal);
                break;
            }
            let arc = self.arcs[a as usize];
            bottleneck = bottleneck.min(arc.reverse);
            i = arc.head;
        }
        // Sink side: the head of `middle` down to the sink.
        let mut i = m.head;
        loop {
            let a = self.nodes[i as usize].parent;
            if a == TERMINAL {
                bottleneck = bottleneck.min(-self.nodes[i as usize].terminal);
                break;
            }
            let arc = self.arcs[a as usize];
            bottleneck = bottleneck.min(arc.residual);
            i = arc.head;
        }

        self.push(middle, bottleneck);
        let mut i = tail;
        loop {
            let a = self.nodes[i as usize].parent;
            if a == TERMINAL {
                self.nodes[i as usize].terminal -= bottleneck;
                if self.nodes[i as usize].terminal == 0 {
                    self.make_orphan(i, true);
                }
                break;
            }
            let arc = self.arcs[a as usize];
            // Flow runs parent → i, along the reverse of the parent arc.
            self.push(arc.sister, bottleneck);
            if arc.reverse == bottleneck {
                self.make_orphan(i, true);
            }
            i = arc.head;
        }
        let mut i = m.head;
        loop {
            let a = self.nodes[i as usize].parent;
            if a == TERMINAL {
                self.nodes[i as usize].terminal += bottleneck;
                if self.nodes[i as usize].terminal == 0 {
                    self.make_orphan(i, true);
                }
                break;
            }
            let arc = self.arcs[a as usize];
            // Flow runs i → parent.
            self.push(a, bottleneck);
            if arc.residual == bottleneck {
                self.make_orphan(i, true);
            }
            i = arc.head;
        }
        self.flow += Capacity::from(bottleneck);
    }

    fn adopt_orphans(&mut self) {
        while let Some(i) = self.orphans.pop_front() {
            self.adopt(i);
        }
    }

    /// Distance from `j` to its tree's terminal along parents, or `None` when the path ends at
    /// an orphan; marks the nodes on the way with the current time.
    #[inline(never)]
    fn origin_distance(&mut self, j: u32) -> Option<u32> {
        let time = self.time;
        let mut d: u32 = 0;
        let mut k = j;
        loop {
            let n = self.nodes[k as usize];
            if n.time == time {
                d = d.saturating_add(n.dist);
                break;
            }
            d += 1;
            if n.parent == TERMINAL {
                let n = &mut self.nodes[k as usize];
                n.time = time;
                n.dist = 1;
                break;
            }
            if n.parent == ORPHAN || n.parent == NONE {
                return None;
            }
            k = self.arcs[n.parent as usize].head;
        }
        // Mark the path so later searches stop early.
        let mut k = j;
        let mut dk = d;
        while self.nodes[k as usize].time != time {
            let n = &mut self.nodes[k as usize];
            n.time = time;
            n.dist = dk;
            dk -= 1;
            k = self.arcs[n.parent as usize].head;
        }
        Some(d)
    }

    /// Finds a new parent for orphan `i` in its tree, or frees it.
    #[inline(never)]
    fn adopt(&mut self, i: u32) {
        let sink_tree = self.nodes[i as usize].in_sink_tree;
        let mut best = NONE;
        let mut best_dist = INFINITE_DISTANCE;
        for a in self.arc_range(i) {
            let arc = self.arcs[a];
            // Residual from the candidate parent towards `i` (source tree) or from `i` (sink).
            let residual = if sink_tree { arc.residual } else { arc.reverse };
            let other = self.nodes[arc.head as usize];
            if residual > 0
                && other.in_sink_tree == sink_tree
                && other.parent != NONE
                && let Some(d) = self.origin_distance(arc.head)
                && d < best_dist
            {
                best = a as u32;
                best_dist = d;
            }
        }
        if best != NONE {
            let time = self.time;
            let n = &mut self.nodes[i as usize];
            n.parent = best;
            n.time = time;
            n.dist = best_dist + 1;
            return;
        }
        // No parent: `i` becomes free; its children become orphans and its tree neighbours
        // that could reach it become active.
        self.nodes[i as usize].parent = NONE;
        for a in self.arc_range(i) {
            let arc = self.arcs[a];
            let j = arc.head;
            let other = self.nodes[j as usize];
            if other.in_sink_tree == sink_tree && other.parent != NONE {
                let residual = if sink_tree { arc.residual } else { arc.reverse };
                if residual > 0 {
                    self.activate(j);
                }
                if other.parent != TERMINAL && other.parent != ORPHAN && self.arcs[other.parent as usize].head == i {
                    self.make_orphan(j, false);
                }
            }
        }
    }
}

/// One arc of a graph given as a list (for [`reference_max_flow`] and tests).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EdgeSpec {
    /// Tail.
    pub from: usize,
    /// Head.
    pub to: usize,
    /// Capacity `from → to`.
    pub capacity: Capacity,
    /// Capacity `to → from`.
    pub reverse: Capacity,
}

/// Edmonds–Karp max-flow on `nodes` nodes with terminal capacities `(source, sink)` per node
/// (non-negative) and the given edges: the plain reference the Boykov–Kolmogorov graph is tested
/// against. Returns the flow and, per node, whether it is reachable from the source in the final
/// residual graph.
pub fn reference_max_flow(terminals: &[(Capacity, Capacity)], edges: &[EdgeSpec]) -> (Capacity, Vec<bool>) {
    let n = terminals.len() + 2;
    let (s, t) = (n - 2, n - 1);
    let mut residual = vec![vec![0 as Capacity; n]; n];
    for (i, &(cs, ct)) in terminals.iter().enumerate() {
        residual[s][i] += cs;
        residual[i][t] += ct;
    }
    for e in edges {
        residual[e.from][e.to] += e.capacity;
        residual[e.to][e.from] += e.reverse;
    }
    let mut flow = 0;
    loop {
        let mut previous = vec![usize::MAX; n];
        previous[s] = s;
        let mut queue = VecDeque::from([s]);
        while let Some(u) = queue.pop_front() {
            for v in 0..n {
                if previous[v] == usize::MAX && residual[u][v] > 0 {
                    previous[v] = u;
                    queue.push_back(v);
                }
            }
        }
        if previous[t] == usize::MAX {
            let reachable = (0..terminals.len()).map(|i| previous[i] != usize::MAX).collect();
            return (flow, reachable);
        }
        let mut bottleneck = Capacity::MAX;
        let mut v = t;
        while v != s {
            let u = previous[v];
            bottleneck = bottleneck.min(residual[u][v]);
            v = u;
        }
        let mut v = t;
        while v != s {
            let u = previous[v];
            residual[u][v] -= bottleneck;
            residual[v][u] += bottleneck;
            v = u;
        }
        flow += bottleneck;
    }
}

/// A binary variable of a [`BinaryEnergy`].
pub type Var = u32;

/// A function of binary variables, `E(x) = constant + Σ unary + Σ pairwise`, minimised exactly
/// by one minimum cut when every pairwise term is submodular (`E(0,1) + E(1,0) ≥ E(0,0) +
/// E(1,1)`; Kolmogorov & Zabih, "What energy functions can be minimized via graph cuts?", PAMI
/// 2004). A variable is 0 on the source side of the cut, 1 on the sink side.
#[derive(Debug, Default, Clone)]
pub struct BinaryEnergy {
    graph: Graph,
    constant: Capacity,
}

impl BinaryEnergy {
    /// An empty energy.
    pub fn new() -> Self {
        Self::default()
    }

    /// Removes every variable and term, keeping the storage.
    pub fn reset(&mut self) {
        self.graph.reset();
        self.constant = 0;
    }

    /// Reserves room for variables and pairwise terms.
    pub fn reserve(&mut self, variables: usize, pairwise: usize) {
        self.graph.reserve(variables, pairwise);
    }

    /// Adds a variable with unary costs `e0` (value 0) and `e1` (value 1).
    pub fn add_variable(&mut self, e0: Capacity, e1: Capacity) -> Var {
        let x = self.graph.add_node();
        self.add_unary(x, e0, e1);
        x
    }

    /// Adds a constant.
    pub fn add_constant(&mut self, value: Capacity) {
        self.constant += value;
    }

    /// Adds unary costs to `x`.
    pub fn add_unary(&mut self, x: Var, e0: Capacity, e1: Capacity) {
        // x = 1 (sink side) cuts the source arc; x = 0 cuts the sink arc.
        self.graph.add_terminal_weights(x, e1, e0);
    }

    /// Adds a pairwise term with table `[E(0,0), E(0,1), E(1,0), E(1,1)]`; it must be
    /// submodular (checked in debug builds).
    pub fn add_pairwise(&mut self, x: Var, y: Var, [e00, e01, e10, e11]: [Capacity; 4]) {
        debug_assert!(e01 + e10 >= e00 + e11, "non-submodular term {e00} {e01} {e10} {e11}");
        // E = E00 + (E10 − E00)·x + (E11 − E10)·y + (E01 + E10 − E00 − E11)·(1 − x)·y
        self.constant += e00;
        self.add_unary(x, 0, e10 - e00);
        self.add_unary(y, 0, e11 - e10);
        let weight = e01 + e10 - e00 - e11;
        if weight > 0 {
            self.graph.add_edge(x, y, weight, 0);
        }
    }

    /// Adds a symmetric Potts term: `penalty` when `x ≠ y`.
    pub fn add_potts(&mut self, x: Var, y: Var, penalty: Capacity) {
        if penalty > 0 {
            self.graph.add_edge(x, y, penalty, penalty);
        }
    }

    /// Forbids `x = 0, y = 1` (an infinite cost).
    pub fn forbid_01(&mut self, x: Var, y: Var) {
        self.graph.add_edge(x, y, INFINITE_CAPACITY, 0);
    }

    /// Minimises the energy; returns its minimum. Read the labelling with [`BinaryEnergy::value`].
    pub fn minimize(&mut self) -> Capacity {
        self.constant + self.graph.max_flow()
    }

    /// The value of `x` in the minimum found.
    pub fn value(&self, x: Var) -> u8 {
        match self.graph.segment(x) {
            Segment::Source => 0,
            Segment::Sink => 1,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self, bound: u64) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (self.0 >> 33) % bound
        }
    }

    fn random_graph(rng: &mut Lcg, nodes: usize, edges: usize, max: u64) -> (Vec<(Capacity, Capacity)>, Vec<EdgeSpec>) {
        let terminals = (0..nodes)
            .map(|_| {
                let source = if rng.next(3) == 0 { rng.next(max) as Capacity } else { 0 };
                let sink = if rng.next(3) == 0 { rng.next(max) as Capacity } else { 0 };
                (source, sink)
            })
            .collect();
        let mut list = Vec::new();
        while list.len() < edges {
            let (from, to) = (rng.next(nodes as u64) as usize, rng.next(nodes as u64) as usize);
            if from != to {
                let capacity = rng.next(max) as Capacity;
                let reverse = if rng.next(2) == 0 { rng.next(max) as Capacity } else { 0 };
                list.push(EdgeSpec {
                    from,
                    to,
                    capacity,
                    reverse,
                });
            }
        }
        (terminals, list)
    }

    /// Capacity of the cut (source side = `source_side`) in the original graph.
    fn cut_capacity(terminals: &[(Capacity, Capacity)], edges: &[EdgeSpec], source_side: &[bool]) -> Capacity {
        let mut cut = 0;
        for (i, &(cs, ct)) in terminals.iter().enumerate() {
            cut += if source_side[i] { ct } else { cs };
        }
        for e in edges {
            if source_side[e.from] && !source_side[e.to] {
                cut += e.capacity;
            }
            if source_side[e.to] && !source_side[e.from] {
                cut += e.reverse;
            }
        }
        cut
    }

    #[test]
    fn boykov_kolmogorov_matches_edmonds_karp_on_random_graphs() {
        let mut rng = Lcg(12);
        for round in 0..400 {
            let nodes = 2 + rng.next(40) as usize;
            let edges = rng.next(4 * nodes as u64) as usize;
            let max = if round % 2 == 0 { 10 } else { 1000 };
            let (terminals, edges) = random_graph(&mut rng, nodes, edges, max);
            let (expected, reachable) = reference_max_flow(&terminals, &edges);

            let mut graph = Graph::new();
            for &(cs, ct) in &terminals {
                let i = graph.add_node();
                graph.add_terminal_weights(i, cs, ct);
            }
            for e in &edges {
                graph.add_edge(e.from as u32, e.to as u32, e.capacity, e.reverse);
            }
            let flow = graph.max_flow();
            assert_eq!(flow, expected, "round {round}");
            // The cut BK reports is a minimum cut: its capacity equals the flow.
            let side: Vec<bool> = (0..nodes).map(|i| graph.segment(i as u32) == Segment::Source).collect();
            assert_eq!(cut_capacity(&terminals, &edges, &side), flow, "round {round}");
            // The reference's cut (nodes reachable from the source) is one too.
            assert_eq!(cut_capacity(&terminals, &edges, &reachable), flow, "round {round}");
        }
    }

    #[test]
    fn storage_is_reused_after_reset() {
        let mut graph = Graph::new();
        for _ in 0..3 {
            graph.reset();
            let (a, b) = (graph.add_node(), graph.add_node());
            graph.add_terminal_weights(a, 5, 0);
            graph.add_terminal_weights(b, 0, 3);
            graph.add_edge(a, b, 4, 0);
            assert_eq!(graph.max_flow(), 3);
            assert_eq!(graph.segment(a), Segment::Source);
            assert_eq!(graph.segment(b), Segment::Source);
        }
    }

    /// Brute force over every labelling.
    fn brute_force(variables: usize, terms: &dyn Fn(&[u8]) -> Capacity) -> Capacity {
        (0..1u32 << variables)
            .map(|bits| {
                let x: Vec<u8> = (0..variables).map(|i| ((bits >> i) & 1) as u8).collect();
                terms(&x)
            })
            .min()
            .unwrap_or(0)
    }

    #[test]
    fn binary_energy_minimum_equals_brute_force() {
        let mut rng = Lcg(99);
        for round in 0..300 {
            let n = 1 + rng.next(8) as usize;
            let unary: Vec<[Capacity; 2]> = (0..n)
                .map(|_| [rng.next(40) as Capacity - 20, rng.next(40) as Capacity - 20])
                .collect();
            let mut pairs = Vec::new();
            for _ in 0..rng.next(12) {
                let (x, y) = (rng.next(n as u64) as usize, rng.next(n as u64) as usize);
                if x == y {
                    continue;
                }
                // A random submodular table.
                let (e00, e11) = (rng.next(20) as Capacity - 10, rng.next(20) as Capacity - 10);
                let e01 = rng.next(20) as Capacity - 10;
                let e10 = (e00 + e11 - e01) + rng.next(10) as Capacity;
                pairs.push((x, y, [e00, e01, e10, e11]));
            }
            let forbidden: Vec<(usize, usize)> = (0..rng.next(3))
                .map(|_| (rng.next(n as u64) as usize, rng.next(n as u64) as usize))
                .filter(|(x, y)| x != y)
                .collect();
            let terms = |x: &[u8]| -> Capacity {
                let mut e = 0;
                for (i, u) in unary.iter().enumerate() {
                    e += u[x[i] as usize];
                }
                for &(a, b, t) in &pairs {
                    e += t[2 * x[a] as usize + x[b] as usize];
                }
                for &(a, b) in &forbidden {
                    if x[a] == 0 && x[b] == 1 {
                        e += INFINITE_CAPACITY;
                    }
                }
                e
            };
            let expected = brute_force(n, &terms);
            let mut energy = BinaryEnergy::new();
            let vars: Vec<Var> = unary.iter().map(|u| energy.add_variable(u[0], u[1])).collect();
            for &(a, b, t) in &pairs {
                energy.add_pairwise(vars[a], vars[b], t);
            }
            for &(a, b) in &forbidden {
                energy.forbid_01(vars[a], vars[b]);
            }
            let minimum = energy.minimize();
            assert_eq!(minimum, expected, "round {round}");
            let labels: Vec<u8> = vars.iter().map(|v| energy.value(*v)).collect();
            assert_eq!(
                terms(&labels),
                minimum,
                "round {round}: the labelling has the minimum energy"
            );
        }
    }
}
