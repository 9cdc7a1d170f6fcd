"""How each placed fragment is held: the used matches that reach it, and whether it lies on a
closed loop of them.

A fragment on a loop is placed by two chains of matches that agree (the assembly graph uses a
match that closes a loop only where it agrees with the tree around it, `forest.grow_forest`); a
fragment held by one match rests on that match alone, and a wrong match that passed
verification puts it wherever that match says. On the corpus's held-out 8-piece objects 330 of
333 fragments on a loop were right (the others near misses, under 2.1% off), those resting on one
match 82-92% (51% on the objects that failed most; docs/benchmarks.md, "How each piece is held"),
so the summary and the viewer name the fragments that rest on one match.
"""
from __future__ import annotations


def held_by(n: int, used: list[tuple[int, int]]) -> tuple[list[int], list[bool]]:
    """The used matches at each fragment and whether it lies on a closed loop of them.

    Parameters
    ----------
    n : the number of fragments
    used : list of (a, b), the fragments each used match joins (two matches of one pair close a loop)

    Returns
    -------
    matches : (n,) list of int, the used matches at each fragment
    on_loop : (n,) list of bool, whether a used match at the fragment lies on a cycle
        (is not a bridge of the graph of used matches)
    """
    adjacent: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    matches = [0] * n
    for k, (a, b) in enumerate(used):
        adjacent[a].append((b, k))
        adjacent[b].append((a, k))
        matches[a] += 1
        matches[b] += 1
    # Tarjan's bridges, iterative: an edge to a child is a bridge where nothing below the child
    # reaches back above it
    order, low = [-1] * n, [0] * n
    bridge = [False] * len(used)
    clock = 0
    for root in range(n):
        if order[root] >= 0:
            continue
        order[root] = low[root] = clock
        clock += 1
        stack = [(root, -1, iter(adjacent[root]))]
        while stack:
            node, via, edges = stack[-1]
            step = next(edges, None)
            if step is None:
                stack.pop()
                if stack:
                    parent = stack[-1][0]
                    low[parent] = min(low[parent], low[node])
                    if low[node] > order[parent]:
                        bridge[via] = True
                continue
            other, k = step
            if k == via:
                continue
            if order[other] >= 0:
                low[node] = min(low[node], order[other])
            else:
                order[other] = low[other] = clock
                clock += 1
                stack.append((other, k, iter(adjacent[other])))
    on_loop = [False] * n
    for k, (a, b) in enumerate(used):
        if not bridge[k]:
            on_loop[a] = on_loop[b] = True
    return matches, on_loop
