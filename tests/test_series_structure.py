"""The XPIC(m) / FMPM(k) series in the compiled step: one loop of S+S whose trip count is the order minus one,
and nothing else that grows with the order (issue 32 item 5).

On an H100 FMPM(8) once cost 23 FLIP steps while XPIC(8) cost 2.6.  The program was not the cause: the step's
optimised HLO is the same size at every order under both fusion policies, and FMPM's loop body is XPIC's.  The
measured runs had turned to NaN (FMPM(k >= 4) at mpm88's dt = 2e-4, 131k particles; benchmarks/README.md "The
series"), and NaN particles all scatter into the grid's first cells, where the GPU's atomic adds queue.
These tests keep the structure that makes an order cost one S+S: a structural check, not a timing one."""

import collections
import os
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import pytest

import jaxmpm as jm

COUNTED = ("scatter", "gather", "while", "conditional")


def _computations(text: str) -> dict:
    """{computation name: [(op, rest of the line)]} of an optimised HLO module's text."""
    computations, current = {}, None
    for line in text.splitlines():
        head = re.match(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$", line)
        if head:
            current = computations.setdefault(head.group(1), [])
            continue
        instruction = re.match(r"^\s+(?:ROOT\s+)?%?[\w.\-]+ = (.*)$", line)
        if instruction and current is not None:
            rest = instruction.group(1)
            if rest.startswith("("):  # a tuple type: skip to its closing parenthesis
                depth = 0
                for end, char in enumerate(rest):
                    depth += (char == "(") - (char == ")")
                    if depth == 0:
                        break
                rest = rest[end + 1:].strip()
            else:
                rest = rest.partition(" ")[2]
            current.append((re.match(r"[\w\-]+", rest).group(0), rest))
    return computations


def _ops(computations: dict, name: str) -> collections.Counter:
    """The ops of computation ``name`` with those of the computations it calls (fusions, reductions)."""
    total = collections.Counter()
    for op, rest in computations[name]:
        total[op] += 1
        for called in re.findall(r"(?:calls|to_apply)=%?([\w.\-]+)", rest):
            total += _ops(computations, called)
    return total


def _structure(scheme, policy: str):
    """(counts of COUNTED ops and of all instructions in the module, [(trip count, body ops)] of its loops) of one
    compiled mpm88 step."""
    setup = jm.scene("mpm88", n_particles=64, n_grid=16, scheme=scheme)
    sim, dt = setup.sim.with_backend(policy), jnp.asarray(setup.dt)
    if hasattr(sim, "with_kernel"):  # the XLA kernel's program, whatever the kernel table picks for this policy
        sim = sim.with_kernel("xla")
    arrays, static = eqx.partition((sim, setup.state), eqx.is_array)

    def step(arrays):
        sim, state = eqx.combine(arrays, static)
        return sim.step(state, dt)

    # the suite's XLA:CPU loop emitters (tests/conftest.py) write a scatter as a loop of its own; compile with the
    # fusion emitters that benchmarks and users get
    options = ({"xla_cpu_use_fusion_emitters": True}
               if "--xla_cpu_use_fusion_emitters=false" in os.environ.get("XLA_FLAGS", "") else {})
    text = jax.jit(step).lower(arrays).compile(compiler_options=options).as_text()
    computations = _computations(text)
    module = collections.Counter(op for body in computations.values() for op, _ in body)
    loops = []
    for body in computations.values():
        for op, rest in body:
            if op == "while":
                trip = re.search(r'"known_trip_count":\{"n":"(\d+)"\}', rest)
                loops.append((int(trip.group(1)) if trip else None,
                              _ops(computations, re.search(r"body=%?([\w.\-]+)", rest).group(1))))
    return {op: module[op] for op in COUNTED} | {"instructions": sum(module.values())}, loops


@pytest.mark.slow
@pytest.mark.parametrize("policy", ["cpu", "gpu"])
def test_an_order_adds_loop_iterations_not_program(policy):
    """FMPM(4) and FMPM(8) compile to the same module (as many scatters, gathers, loops, conditionals and
    instructions) with one loop, of trip count k - 1, whose body scatters once (S+); FMPM(8)'s loop is XPIC(8)'s.
    So each order costs one S+S application, under the CPU policy and the GPU one (the program a GPU runs,
    whose loop holds no stage boundary: a conditional there would cost a host round trip per order)."""
    (fmpm4, fmpm4_loops), (fmpm8, fmpm8_loops) = (_structure(jm.FMPM(order=k), policy) for k in (4, 8))
    _, xpic8_loops = _structure(jm.XPIC(order=8), policy)
    assert fmpm4 == fmpm8, f"the FMPM step grows with the order under the {policy} policy"
    assert [trip for trip, _ in fmpm4_loops] == [3] and [trip for trip, _ in fmpm8_loops] == [7]
    body = fmpm8_loops[0][1]
    assert fmpm4_loops[0][1] == body == xpic8_loops[0][1]
    assert body["scatter"] == 1 and body["gather"] >= 1 and body["while"] == 0
    if policy == "gpu":
        assert body["conditional"] == 0
