"""How each placed fragment is held (relicgpu.heap.support)."""
import numpy as np

from relicgpu.heap.support import held_by


def _on_loop_by_removal(n, used):
    """A fragment is on a loop where removing one of its used matches leaves its ends joined."""
    out = [False] * n
    for k, (a, b) in enumerate(used):
        rest = used[:k] + used[k + 1:]
        seen, todo = {a}, [a]
        while todo:
            x = todo.pop()
            for p, q in rest:
                for u, v in ((p, q), (q, p)):
                    if u == x and v not in seen:
                        seen.add(v)
                        todo.append(v)
        if b in seen:
            out[a] = out[b] = True
    return out


def test_a_triangle_holds_its_three_and_a_tail_rests_on_single_matches():
    matches, on_loop = held_by(6, [(0, 1), (1, 2), (2, 0), (2, 3), (3, 4)])
    assert matches == [2, 2, 3, 2, 1, 0]
    assert on_loop == [True, True, True, False, False, False]


def test_two_matches_of_one_pair_close_a_loop():
    assert held_by(4, [(0, 1), (1, 0), (2, 3)]) == ([2, 2, 1, 1], [True, True, False, False])
    assert held_by(3, []) == ([0, 0, 0], [False, False, False])


def test_random_graphs_agree_with_removing_each_match():
    rng = np.random.default_rng(5)
    for _ in range(200):
        n = int(rng.integers(2, 14))
        used = [tuple(int(x) for x in rng.choice(n, 2, replace=False)) for _ in range(int(rng.integers(0, 16)))]
        matches, on_loop = held_by(n, used)
        assert on_loop == _on_loop_by_removal(n, used), used
        assert matches == [sum(i in e for e in used) for i in range(n)]


def test_a_long_chain_does_not_recurse():
    n = 20000  # a path, then closed: far past Python's recursion limit
    path = [(i, i + 1) for i in range(n - 1)]
    assert not any(held_by(n, path)[1])
    assert all(held_by(n, path + [(n - 1, 0)])[1])
