"""The renderer choice: MUJOCO_GL wins; otherwise the fastest backend whose frames equal OSMesa's, by a margin."""
import json

from jepa_envs.tasks import render


def _fake_probes(monkeypatch, rows):
    monkeypatch.setattr(render, "probe", lambda name, frames=20, size=84, **kw: dict(rows[name], renderer=name))


def test_a_clearly_faster_backend_with_identical_frames_is_chosen(monkeypatch):
    _fake_probes(monkeypatch, {"egl": {"ms_per_frame": 40.0, "digest": "a"},
                               "osmesa": {"ms_per_frame": 80.0, "digest": "a"}})
    assert render.measure()["choice"] == "egl"


def test_osmesa_stays_unless_another_is_faster_by_the_margin_or_renders_differently(monkeypatch):
    _fake_probes(monkeypatch, {"egl": {"ms_per_frame": 75.0, "digest": "a"},
                               "osmesa": {"ms_per_frame": 80.0, "digest": "a"}})
    result = render.measure()
    assert result["choice"] == "osmesa" and "not 10% faster" in result["why"]
    _fake_probes(monkeypatch, {"egl": {"ms_per_frame": 10.0, "digest": "b"},
                               "osmesa": {"ms_per_frame": 80.0, "digest": "a"}})
    result = render.measure()
    assert result["choice"] == "osmesa" and "egl renders different frames, not used" in result["why"]
    _fake_probes(monkeypatch, {"egl": {"error": "no EGL"}, "osmesa": {"error": "no OSMesa"}})
    assert render.measure()["choice"] == "osmesa"


def test_the_user_setting_wins_and_the_measurement_is_cached(monkeypatch, tmp_path):
    monkeypatch.setattr(render, "CACHE", tmp_path / "renderer.json")
    monkeypatch.setenv("MUJOCO_GL", "glfw")
    assert render.choose_renderer(verbose=False) == "glfw"
    monkeypatch.delenv("MUJOCO_GL")
    calls = []
    monkeypatch.setattr(render, "measure", lambda: calls.append(1) or {"results": [], "choice": "egl", "why": "x"})
    assert render.choose_renderer(verbose=False) == "egl" and render.choose_renderer(verbose=False) == "egl"
    assert calls == [1] and json.loads((tmp_path / "renderer.json").read_text())["choice"] == "egl"
    monkeypatch.setattr(render, "_machine_key", lambda: "another machine")   # a new machine measures again
    render.choose_renderer(verbose=False)
    assert calls == [1, 1]
