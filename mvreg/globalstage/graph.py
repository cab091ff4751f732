"""Graphs of agreeing pairs ({scan: set of partner scans}): cycles, bridges, the main
2-edge-connected block and the groups that hang on the rest by one pair. Pure functions
on small dicts; used by :mod:`mvreg.globalstage.verify`."""

from __future__ import annotations

__all__ = ["bridge_groups", "bridges", "conflict_cuts", "main_block", "on_cycle"]


def on_cycle(graph: dict[int, set[int]]) -> set[int]:
    """Scans with two neighbours that are connected without them (the scan lies on a
    cycle of the graph)."""
    out = set()
    for s, nbrs in graph.items():
        if len(nbrs) < 2:
            continue
        # Components of the graph without s, reached from s's neighbours.
        label: dict[int, int] = {}
        for start in nbrs:
            if start in label:
                out.add(s)
                break
            stack = [start]
            label[start] = start
            while stack:
                a = stack.pop()
                for b in graph[a]:
                    if b != s and b not in label:
                        label[b] = start
                        stack.append(b)
    return out


def bridges(graph: dict[int, set[int]]) -> set[frozenset]:
    """The pairs of the graph whose removal disconnects it (Tarjan, iterative)."""
    index: dict[int, int] = {}
    low: dict[int, int] = {}
    out: set[frozenset] = set()
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        index[root] = low[root] = counter
        counter += 1
        stack = [(root, None, iter(sorted(graph[root])))]
        while stack:
            v, parent, it = stack[-1]
            w = next(it, None)
            if w is None:
                stack.pop()
                if parent is not None:
                    low[parent] = min(low[parent], low[v])
                    if low[v] > index[parent]:
                        out.add(frozenset((parent, v)))
                continue
            if w == parent:
                continue
            if w in index:
                low[v] = min(low[v], index[w])
            else:
                index[w] = low[w] = counter
                counter += 1
                stack.append((w, v, iter(sorted(graph[w]))))
    return out


def _reach(graph: dict[int, set[int]], start: int, cut: set[frozenset]) -> set[int]:
    """Scans reached from ``start`` without crossing the pairs in ``cut``."""
    seen, todo = {start}, [start]
    while todo:
        a = todo.pop()
        for b in graph[a]:
            if b not in seen and frozenset((a, b)) not in cut:
                seen.add(b)
                todo.append(b)
    return seen


def one_side(graph: dict[int, set[int]], s: int, support) -> list[int]:
    """The scans of ``support`` on the side of ``s`` that holds most of them: the
    components of the graph without ``s``, the one with the most of ``support`` (ties:
    the lowest scan index). Two scans on different sides are placed relative to each
    other only through ``s`` itself, so their fitting ``s`` confirms nothing; two on one
    side were placed without ``s``, and ``s`` fitting both closes a loop."""
    rest = {a: graph[a] - {s} for a in graph if a != s}
    best: list[int] = []
    seen: set[int] = set()
    for k in sorted(support):
        if k in seen or k not in rest:
            continue
        side = _reach(rest, k, set())
        seen |= side
        mine = [j for j in support if j in side]
        if len(mine) > len(best):
            best = mine
    return sorted(best)


def main_block(graph: dict[int, set[int]]) -> set[int]:
    """The largest 2-edge-connected block of the graph (ties: the one holding the lowest
    scan index): the scans that stay connected when any one pair is removed. A group of
    scans that agree with each other but hang on the rest by a single pair (a bridge) is
    outside it: the group's place relative to the rest rests on that one pair."""
    cut = bridges(graph)
    seen: set[int] = set()
    blocks = []
    for s in sorted(graph):
        if s not in seen:
            block = _reach(graph, s, cut)
            seen |= block
            blocks.append(block)
    best = max(blocks, key=lambda b: (len(b), -min(b)), default=set())
    return best if len(best) >= 3 else set()


def bridge_groups(graph: dict[int, set[int]]) -> list[tuple[list[int], list[int]]]:
    """For each bridge of the graph whose smaller side (ties: the side without the lowest
    scan index) has at least two scans, (that side, the other side): groups of scans
    placed relative to each other by that one pair. Smallest first, each once."""
    groups = {}
    for edge in sorted(bridges(graph), key=sorted):
        a, b = sorted(edge)
        side_a, side_b = _reach(graph, a, {edge}), _reach(graph, b, {edge})
        side, rest = (
            (side_b, side_a)
            if (len(side_b), min(side_a)) <= (len(side_a), min(side_b))
            else (side_a, side_b)
        )
        if len(side) >= 2:
            groups[tuple(sorted(side))] = sorted(rest)
    return [(list(g), groups[g]) for g in sorted(groups, key=lambda g: (len(g), g))]


def conflict_cuts(graph: dict[int, set[int]], conflicts, weakness) -> list[frozenset]:
    """Bridges to cut so that no two conflicting scans stay connected through one.

    ``conflicts``: pairs of scans (any iterable of 2-tuples) whose views contradict each
    other under the solve (a free-space test). Two scans joined only through bridges are
    placed relative to each other by those pairs alone, so a contradiction between them
    indicts a bridge on the way. Greedy: the bridge separating the most conflicting pairs
    is cut first (ties: the one cutting off fewer scans, so the fewest poses are given up,
    then the larger ``weakness(pair)``, then the lower scans), the bridges
    are found again, until no bridge separates a conflicting pair still connected.
    Conflicts inside a 2-edge-connected block are left alone (no single pair explains
    them). Returns the cut pairs in the order cut."""
    graph = {a: set(b) for a, b in graph.items()}
    pending = {frozenset(c) for c in conflicts if len(set(c)) == 2 and set(c) <= graph.keys()}
    cuts: list[frozenset] = []
    while pending:
        best, best_key = None, None
        for edge in bridges(graph):
            a, b = sorted(edge)
            side = _reach(graph, a, {edge})
            if b in side:
                continue
            other = _reach(graph, b, {edge})
            n = sum(1 for c in pending if len(c & side) == 1 and len(c & other) == 1)
            key = (n, -min(len(side), len(other)), weakness(edge), -a, -b)
            if n and (best_key is None or key > best_key):
                best, best_key = edge, key
        if best is None:
            break
        a, b = sorted(best)
        graph[a].discard(b)
        graph[b].discard(a)
        cuts.append(best)
        pending = {c for c in pending if min(c) in _reach(graph, max(c), set())}
    return cuts
