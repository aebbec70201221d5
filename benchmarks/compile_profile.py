"""Where a program's compile time goes: XLA:CPU's kernels, each with the time its code generator took, its size,
its role and the Python line that made it.

    python benchmarks/compile_profile.py                                # mpm88's gradient (compile_time.py's)
    python benchmarks/compile_profile.py --scene disks --program rollout --top 20
    python benchmarks/compile_profile.py --scene mpm88 --program gradient --markdown profile.md --json out.json

The programs are ``compile_time.py``'s (``rollout``, ``gradient``, ``step``, ``transpose``, ``ensemble``,
``calibrate``; float64, the scene's steps unless ``--steps``).  The script lowers one, compiles it under
``jax.profiler`` with JAX's persistent cache off, and reads the trace: the whole compilation
(``PjRtCpuClient::Compile``), XLA's HLO passes, the emission of each kernel (one ``FusionCompiler::Compile``
event per kernel: its module name and its operation count) and LLVM's code generation of them all (``Codegen``).
XLA emits identical kernels once, so the program may hold more kernel instructions (``launches``: its fusions)
than kernels emitted.  Each kernel is mapped to its instruction in the compiled program
(``compiled.as_text()``) and given:

* its **role**: ``boundary predicate`` -- the scalar kernel that computes a stage boundary's always-true
  predicate (the operand of an XLA conditional; ``jaxmpm.transfer.backend``), ``untaken branch`` -- a kernel of
  a conditional's branch that never runs (the zeros of a boundary's other branch: compiled, never executed),
  ``in a branch`` -- a kernel of the taken branch, or ``step`` for the rest;
* the Python line that produced it (``cpu_profile.source_lines``: jaxmpm's innermost frames).

The program is compiled for the CPU (``JAX_PLATFORMS=cpu`` unless set): the events read are XLA:CPU's.  The tables
list the kernels by emission time, then the sums by role and by kind (the kernel's name without its
number).  Kernel emission runs on XLA's compile threads, so its sum may exceed the wall time of the compilation.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

PROGRAMS = ("rollout", "gradient", "step", "transpose", "ensemble", "calibrate")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="mpm88", help="one of compile_time.py's scene set-ups (default mpm88)")
    p.add_argument("--program", choices=PROGRAMS, default="gradient")
    p.add_argument("--steps", type=int, default=None, help="steps of the rollout (default: the scene's)")
    p.add_argument("--top", type=int, default=30, help="kernels listed, the slowest to emit first (default 30)")
    p.add_argument("--markdown", type=Path, default=None, help="also write the tables to this file")
    p.add_argument("--json", type=Path, default=None, help="also write every number to this file")
    return p.parse_args(argv)


# ------------------------------------------------------------------------------------ the compiled program
def instruction(module: str) -> str:
    """The compiled program's instruction behind a kernel module's name (``add_fusion.3_kernel_module``,
    ``__compute_module_wrapped_copy``, ``wrapped_scatter``)."""
    return re.sub(r"_kernel_module$", "", re.sub(r"^__compute_module_", "", module))


def kind(name: str) -> str:
    """A kernel's kind: its instruction's name without the number XLA appends (``add_fusion.3`` -> ``add_fusion``)."""
    return re.sub(r"\.\d+$", "", name)


def roles(hlo_text: str) -> dict:
    """{instruction name: role} for the instructions a stage boundary adds: ``boundary predicate`` (a
    conditional's index operand), ``untaken branch`` (an instruction of branch 0 of a conditional, the
    false branch of ``lax.cond``, which a boundary never takes) and ``in a branch`` (of any other branch)."""
    bodies, current = {}, None
    for line in hlo_text.split("\n"):
        head = re.match(r"^(?:ENTRY )?%([\w.\-]+) .*\{$", line)
        if head:
            current = bodies.setdefault(head.group(1), [])
        elif line.startswith("}"):
            current = None
        elif current is not None:
            m = re.match(r"^\s+(?:ROOT )?%([\w.\-]+) = ", line)
            if m:
                current.append(m.group(1))
    out = {}
    for m in re.finditer(r" conditional\(%([\w.\-]+)[^\n]*?branch_computations=\{([^}]*)\}", hlo_text):
        out[m.group(1)] = "boundary predicate"
        for i, branch in enumerate(re.findall(r"%([\w.\-]+)", m.group(2))):
            for name in bodies.get(branch, ()):
                out.setdefault(name, "untaken branch" if i == 0 else "in a branch")
    return out


def profile(scene: str, program: str, steps: int | None = None) -> dict:
    """Compile ``program`` of ``scene`` (``compile_time._program``) under the profiler; the numbers of the
    module docstring, times in ms."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import compile_time as ct
    from cpu_profile import source_lines, trace_events

    steps = steps or ct.SCENES[scene][2]
    fn, args, steps, particles = ct._program(scene, program, steps)
    lowered = jax.jit(fn).lower(*args)
    cached = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)  # a cache hit would compile nothing
    folder = tempfile.mkdtemp(prefix="jaxmpm-compile-trace-")
    try:
        tic, cpu = time.perf_counter(), time.process_time()
        with jax.profiler.trace(folder):
            compiled = lowered.compile()
        wall, cpu = time.perf_counter() - tic, time.process_time() - cpu
        events = trace_events(folder)
        if events is None:
            raise RuntimeError(f"jax.profiler wrote no trace under {folder}")
        events = [e for e in events if e.get("ph") == "X" and "dur" in e]  # the complete events, with their time
    finally:
        jax.config.update("jax_enable_compilation_cache", cached)
        shutil.rmtree(folder, ignore_errors=True)
    text = compiled.as_text()
    where, role = source_lines(text), roles(text)

    def total(prefix):
        return sum(e["dur"] for e in events if e["name"].startswith(prefix)) / 1e3

    kernels = []
    for e in events:
        if e["name"] != "FusionCompiler::Compile":
            continue
        a = e.get("args", {})
        name = instruction(a.get("module", "?"))
        kernels.append({"kernel": name, "kind": kind(name), "emit_ms": e["dur"] / 1e3,
                        "ops": int(a.get("op_count", 0) or 0), "role": role.get(name, "step"),
                        "source": where.get(name, "")})
    kernels.sort(key=lambda k: -k["emit_ms"])
    launches = re.findall(r"^\s+(?:ROOT )?%([\w.\-]+) = [^\n]*? fusion\(", text, flags=re.M)
    return {"scene": scene, "program": program, "steps": steps, "particles": particles,
            "compile_wall_s": wall, "compile_cpu_s": cpu, "backend_ms": total("PjRtCpuClient::Compile"),
            "hlo_passes_ms": total("HLO passes"), "emit_ms": sum(k["emit_ms"] for k in kernels),
            "codegen_ms": total("Codegen"), "launches": len(launches),
            "launches_by_role": dict(collections.Counter(role.get(name, "step") for name in launches)),
            "kernels": kernels}


def summary(kernels: list, key: str) -> list:
    """[(key value, kernels, emission ms, operations)], the slowest first."""
    sums = collections.defaultdict(lambda: [0, 0.0, 0])
    for k in kernels:
        s = sums[k[key]]
        s[0] += 1
        s[1] += k["emit_ms"]
        s[2] += k["ops"]
    return sorted(((name, *v) for name, v in sums.items()), key=lambda r: -r[2])


def report(r: dict, top: int) -> str:
    n = len(r["kernels"])
    lines = [f"{r['scene']} {r['program']} ({r['particles']} particles, {r['steps']} steps): compiled in "
             f"{r['compile_wall_s']:.2f} s wall, {r['compile_cpu_s']:.2f} CPU s; XLA backend {r['backend_ms']:.0f} ms, "
             f"HLO passes {r['hlo_passes_ms']:.0f} ms, {n} kernels emitted in {r['emit_ms']:.0f} ms "
             f"({r['emit_ms'] / max(n, 1):.1f} ms each) for the program's {r['launches']} kernel instructions "
             f"(identical kernels are emitted once), LLVM code generation {r['codegen_ms']:.0f} ms", "",
             "| kernel | emit ms | ops | role | source |", "|---|---|---|---|---|"]
    lines += [f"| {k['kernel']} | {k['emit_ms']:.1f} | {k['ops']} | {k['role']} | {k['source']} |"
              for k in r["kernels"][:top]]
    if not n:
        lines += ["", "No kernel emission in the trace: XLA:CPU's fusion emitters are off "
                  "(--xla_cpu_use_fusion_emitters=false), and its older emitters work inside LLVM's code generation."]
    lines += ["", "Kernel instructions by role: " + ", ".join(f"{role} {count}" for role, count in
                                                       sorted(r["launches_by_role"].items(), key=lambda kv: -kv[1]))]
    for key, title in (("role", "role"), ("kind", "kind")):
        lines += ["", f"| {title} | kernels | emit ms | ops |", "|---|---|---|---|"]
        lines += [f"| {name} | {count} | {ms:.0f} | {ops} |" for name, count, ms, ops in summary(r["kernels"], key)]
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("JAXMPM_CACHE", "0")  # before jaxmpm is imported: nothing read back from disk
    os.environ.setdefault("JAX_PLATFORMS", "cpu")  # the events read are XLA:CPU's
    r = profile(args.scene, args.program, args.steps)
    text = report(r, args.top)
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")
    if args.json:
        args.json.write_text(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
