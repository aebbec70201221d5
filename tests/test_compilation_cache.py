"""jm.compilation_cache: compiled programs kept on disk and reused by a later compilation of the
same program (JAX's persistent cache), and clear errors for bad arguments."""

import subprocess
import sys
import textwrap

import pytest

import jaxmpm as jm

SCRIPT = textwrap.dedent("""
    import sys
    import jax, jax.numpy as jnp, jax.monitoring
    import jaxmpm as jm
    events = []
    jax.monitoring.register_event_listener(lambda e, **kw: events.append(e))
    early = jax.jit(lambda x: x + 1)(1.0)  # a compilation before the call: the cache still takes effect
    folder = jm.compilation_cache(sys.argv[1], min_compile_seconds=0)
    assert jax.config.jax_compilation_cache_dir == str(folder)
    f = lambda x: jnp.sin(x) * 2
    first = jax.jit(f)(1.0)
    assert any(folder.iterdir()), "nothing was written to the cache"
    jax.clear_caches()  # forget the in-memory executables: the next call must come from the disk
    second = jax.jit(f)(1.0)
    assert float(first) == float(second)
    print("hits", events.count("/jax/compilation_cache/cache_hits"))
""")


def test_a_compiled_program_is_reused_from_the_disk(tmp_path):
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path / "xla")], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert "hits 1" in out.stdout, out.stdout


def test_default_folder_and_bad_arguments(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXMPM_CACHE_DIR", str(tmp_path / "here"))
    from jaxmpm.run.cache import default_cache_dir

    assert default_cache_dir() == tmp_path / "here"
    monkeypatch.delenv("JAXMPM_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "jaxmpm" / "xla"
    with pytest.raises(jm.InputError, match="min_compile_seconds"):
        jm.compilation_cache(tmp_path, min_compile_seconds=-1)
    a_file = tmp_path / "file"
    a_file.write_text("")
    with pytest.raises(jm.InputError, match="cannot create the folder"):
        jm.compilation_cache(a_file)
