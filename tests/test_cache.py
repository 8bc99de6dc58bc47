"""The command line's persistent compilation cache: where it goes, and switched off."""

from pathlib import Path

from jaxafm.cli import cache


def test_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(cache.CACHE_VARIABLE, str(tmp_path / "xla"))
    assert cache.cache_dir() == tmp_path / "xla"
    monkeypatch.setenv(cache.CACHE_VARIABLE, "off")
    assert cache.cache_dir() is None
    monkeypatch.delenv(cache.CACHE_VARIABLE)
    assert cache.cache_dir() == Path.home() / ".cache" / "jaxafm" / "xla"


def test_a_cache_jax_was_given_is_kept(monkeypatch, tmp_path):
    import jax

    given = jax.config.jax_compilation_cache_dir  # the test session's own (tests/conftest.py)
    assert given
    monkeypatch.setenv(cache.CACHE_VARIABLE, str(tmp_path / "elsewhere"))
    assert cache.enable_compilation_cache() == Path(given)
    assert jax.config.jax_compilation_cache_dir == given
    assert not (tmp_path / "elsewhere").exists()
