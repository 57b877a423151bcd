"""``vlocnetpp bench``: the quick run produces every figure (with its target and the times behind
it, consistent with each other), the ResNet-50 yardstick is the standard one, timing is
interleaved, and bad settings are one-line errors. No speed threshold is checked here."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os

import pytest
import torch
from model_fixtures import single_thread
from torch.utils.flop_counter import FlopCounterMode

from vlocnetpp_core.bench import TARGETS, BenchSettings, format_table
from vlocnetpp_core.bench.resnet50 import ResNet50
from vlocnetpp_core.bench.timing import interleaved
from vlocnetpp_core.cli import main

FIGURES = ("cached_vs_recompute_speedup", "mtl_step_over_resnet50", "node_latency_over_step", "lite_hz",
           "converter_speed_over_png_decode", "synth_fps", "peak_rss_mb")


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> dict:
    """``vlocnetpp bench --quick --json`` (one thread: the suite runs on a shared 2-core machine)."""
    folder = tmp_path_factory.mktemp("bench")
    (folder / "bench.yaml").write_text("threads: 1\nnode_repetitions: 4\nconverter_frames: 12\n")
    mp = pytest.MonkeyPatch()
    mp.setenv("ROS_DOMAIN_ID", str(30 + os.getpid() % 60))  # the node and its probe on a domain of their own
    mp.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    mp.setenv("VLOCNETPP_CACHE", str(folder / "cache"))
    out = io.StringIO()
    try:
        with single_thread(), contextlib.redirect_stdout(out):
            code = main(["bench", "--quick", "--json", "--config", str(folder / "bench.yaml")])
    finally:
        mp.undo()
    assert code == 0
    return json.loads(out.getvalue())


def test_quick_json_has_every_figure_with_numbers(report):
    for key in FIGURES + ("paper_step_ms", "lite_hz_torch", "lite_hz_onnx", "mtl_step_over_resnet50_torch", "mtl_step_over_resnet50_onnx"):
        value = report[key]
        assert isinstance(value, (int, float)) and math.isfinite(value) and value > 0, key
    assert set(report["targets"]) == set(TARGETS)
    for name, entry in report["targets"].items():
        assert entry["value"] == report[name]
        if entry["target"] is None:
            assert entry["met"] is None
        else:
            assert entry["met"] == (entry["value"] >= entry["target"] if entry["compare"] == ">=" else entry["value"] <= entry["target"])
    assert report["targets"]["cached_vs_recompute_speedup"]["target"] == 1.4
    assert report["targets"]["lite_hz"]["target"] == 15.0


def test_ratios_are_the_quotients_of_the_reported_times(report):
    t = report["times_ms"]
    assert report["cached_vs_recompute_speedup"] == pytest.approx(t["paper_step_recompute"] / t["paper_step_cached"], rel=1e-3)
    assert report["mtl_step_over_resnet50_torch"] == pytest.approx(t["paper_step_cached"] / t["resnet50_forward"], rel=1e-3)
    assert report["mtl_step_over_resnet50_onnx"] == pytest.approx(t["paper_step_onnx"] / t["resnet50_forward"], rel=1e-3)
    assert report["mtl_step_over_resnet50"] == min(report["mtl_step_over_resnet50_torch"], report["mtl_step_over_resnet50_onnx"])
    assert report["paper_step_ms"] == pytest.approx(t["paper_step_cached" if report["paper_backend"] == "torch" else "paper_step_onnx"], rel=1e-3)
    assert report["node_latency_over_step"] == pytest.approx(t["node_latency"] / t["node_bare_step"], rel=1e-3)
    assert report["lite_hz"] == pytest.approx(1000.0 / t[f"lite_step_{report['lite_backend']}"], rel=1e-3)
    assert report["lite_hz"] == max(report["lite_hz_torch"], report["lite_hz_onnx"])
    assert report["converter_speed_over_png_decode"] == pytest.approx(t["png_decode_frame"] / t["converter_frame"], rel=1e-3)
    assert report["synth_fps"] == pytest.approx(1000.0 / t["synth_frame"], rel=1e-3)


def test_quick_run_says_what_it_measured(report):
    assert report["quick"] is True and report["paper_input_size"] == [224, 128]
    assert any(n.startswith("quick:") for n in report["notes"])
    assert report["lite_input_size"] == [224, 128] and report["camera_size"] == [640, 360]
    assert report["machine"]["torch_threads"] == 1 and report["settings"]["converter_frames"] == 12
    assert report["converter_frames"] == 12 and report["converter_bag_mb"] > 0
    assert 50 < report["peak_rss_mb"] < 100_000 and report["node_rss_mb"] <= report["peak_rss_mb"]  # a node with torch loaded
    table = format_table(report)
    for name in TARGETS:
        assert name in table
    assert "load average" in table and "note: quick" in table


def test_resnet50_is_the_standard_one():
    """25.6 M parameters and 9.34 GMAC at 448x256, as torchvision's resnet50 (the DESIGN's yardstick)."""
    with single_thread():
        model = ResNet50().eval()
        assert sum(p.numel() for p in model.parameters()) == 25_557_032
        counter = FlopCounterMode(display=False)
        with counter, torch.inference_mode():
            assert model(torch.zeros(1, 3, 256, 448)).shape == (1, 1000)
    assert counter.get_total_flops() / 2e9 == pytest.approx(9.34, abs=0.01)


def test_interleaved_rotates_the_order_and_cleans_up_untimed():
    calls, cleaned = [], []
    times = interleaved({"a": lambda: calls.append("a"), "b": lambda: calls.append("b"), "c": lambda: calls.append("c")},
                        repetitions=3, warmup=1, after=cleaned.append)
    assert calls == ["a", "b", "c", "a", "b", "c", "b", "c", "a", "c", "a", "b"]  # warm-up, then each round starts elsewhere
    assert cleaned == calls and all(len(v) == 3 and min(v) >= 0 for v in times.values())


def test_bad_settings_are_one_line_errors(tmp_path, capsys):
    cfg = tmp_path / "b.yaml"
    for text, expected in (("repetition: 3\n", "unknown bench setting"), ("camera_size: [640]\n", "camera_size"),
                           ("threads: -1\n", "threads"), ("node_backend: trt\n", "node_backend"), ("[1, 2]\n", "mapping")):
        cfg.write_text(text)
        assert main(["bench", "--quick", "--config", str(cfg)]) == 2
        err = capsys.readouterr().err
        assert expected in err and str(cfg) in err and len(err.strip().splitlines()) == 1, err
    assert main(["bench", "--config", str(tmp_path / "none.yaml")]) == 2
    assert "none.yaml" in capsys.readouterr().err
    assert main(["bench", "--device", "tpu"]) == 2
    assert "--device" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert main(["bench", "--quick", "--device", "cuda"]) == 2
        assert "CUDA is not available" in capsys.readouterr().err


def test_settings_override_only_what_the_file_names():
    s = BenchSettings.quick().updated({"threads": 2, "paper_input_size": [448, 256]}, "x.yaml")
    assert s.threads == 2 and s.paper_input_size == (448, 256) and s.repetitions == BenchSettings.quick().repetitions
