"""``vlocnetpp bench``: the quick run produces every figure (with its target and the times behind
it, consistent with each other), the ResNet-50 yardstick is the standard one, timing is
interleaved, and bad settings are one-line errors. No speed threshold is checked here."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from model_fixtures import single_thread
from torch.utils.flop_counter import FlopCounterMode

from vlocnetpp_core.bench import TARGETS, BenchSettings, format_table
from vlocnetpp_core.bench.cuda_graph import CudaGraphStep
from vlocnetpp_core.bench.resnet50 import ResNet50
from vlocnetpp_core.bench.timing import interleaved
from vlocnetpp_core.cli import main
from vlocnetpp_core.model import VLocNetPP, load_model_config

FIGURES = (
    "cached_vs_recompute_speedup",
    "mtl_step_over_resnet50",
    "node_latency_over_step",
    "lite_hz",
    "converter_speed_over_png_decode",
    "synth_fps",
    "train_nchw_over_nhwc",
    "peak_rss_mb",
    "soak_answered_share",
    "soak_latency_p99_ms",
)
SOAK_MINUTES = 0.3  # the soak's figures and files; its 10-minute run is a benchmark (docs/performance.md)


def _map_of_the_bench_frames(folder):
    """A keyframe map of the visit the bench's frames come from (the first test visit of seed 0 at 20 Hz), so the
    refinement figures refine without the full campus map (which is built, not shipped: docs/refinement.md)."""
    from vlocnetpp_core.data import open_dataset
    from vlocnetpp_core.mapping.build import build_map
    from vlocnetpp_core.synth import render_dataset

    render_dataset(
        folder / "visit", seed=0, train_loops=0, test_loops=1, frames_per_loop=40, frame_interval=0.05, progress=False
    )
    return build_map([open_dataset(folder / "visit", None, "test")], spacing_m=0.5, progress=False).save(
        folder / "visit.map.npz"
    )


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> dict:
    """``vlocnetpp bench --quick --json`` (one thread: the suite runs on a shared 2-core machine)."""
    folder = tmp_path_factory.mktemp("bench")
    campus_map = _map_of_the_bench_frames(folder)
    (folder / "bench.yaml").write_text(
        f"threads: 1\nnode_repetitions: 4\nconverter_frames: 12\nrefinement_map: {campus_map}\n"
        f"soak_minutes: {SOAK_MINUTES}\nsoak_out: {folder / 'soak'}\n"
    )
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
    for key in FIGURES + (
        "paper_step_ms",
        "lite_hz_torch",
        "lite_hz_onnx",
        "mtl_step_over_resnet50_torch",
        "mtl_step_over_resnet50_onnx",
    ):
        value = report[key]
        assert isinstance(value, (int, float)) and math.isfinite(value) and value > 0, key
    assert set(report["targets"]) == set(TARGETS)
    for name, entry in report["targets"].items():
        assert entry["value"] == report[name]
        if entry["target"] is None:
            assert entry["met"] is None
        else:
            assert entry["met"] == (
                entry["value"] >= entry["target"] if entry["compare"] == ">=" else entry["value"] <= entry["target"]
            )
    assert report["targets"]["cached_vs_recompute_speedup"]["target"] == 1.4
    assert report["targets"]["lite_hz"]["target"] == 15.0
    assert "mtl_step_over_resnet50_cuda_graph" not in report  # CUDA only


def test_compute_ratio_is_reported(report):
    """The paper step's multiply-accumulates over the ResNet-50's: the ratio a backend as efficient as
    the yardstick would measure (3.94x at the paper's 448x256, docs/performance.md)."""
    t = report["times_ms"]
    assert report["mtl_gmac_over_resnet50"] == pytest.approx(report["paper_step_gmac"] / report["resnet50_gmac"])
    assert report["resnet50_gmac"] == pytest.approx(9.34 * (224 * 128) / (448 * 256), rel=0.01)  # quick: 224x128
    assert 3.5 < report["mtl_gmac_over_resnet50"] < 4.5
    assert "paper_step_gmac" not in t and any("in compute the step is" in n for n in report["notes"])


def test_ratios_are_the_quotients_of_the_reported_times(report):
    t = report["times_ms"]
    assert report["cached_vs_recompute_speedup"] == pytest.approx(
        t["paper_step_recompute"] / t["paper_step_cached"], rel=1e-3
    )
    assert report["mtl_step_over_resnet50_torch"] == pytest.approx(
        t["paper_step_cached"] / t["resnet50_forward"], rel=1e-3
    )
    assert report["mtl_step_over_resnet50_onnx"] == pytest.approx(
        t["paper_step_onnx"] / t["resnet50_forward"], rel=1e-3
    )
    assert report["mtl_step_over_resnet50"] == min(
        report["mtl_step_over_resnet50_torch"], report["mtl_step_over_resnet50_onnx"]
    )
    assert report["paper_step_ms"] == pytest.approx(
        t["paper_step_cached" if report["paper_backend"] == "torch" else "paper_step_onnx"], rel=1e-3
    )
    assert report["node_latency_over_step"] == pytest.approx(t["node_latency"] / t["node_bare_step"], rel=1e-3)
    assert report["lite_hz"] == pytest.approx(1000.0 / t[f"lite_step_{report['lite_backend']}"], rel=1e-3)
    assert report["lite_hz"] == max(report["lite_hz_torch"], report["lite_hz_onnx"])
    assert report["converter_speed_over_png_decode"] == pytest.approx(
        t["png_decode_frame"] / t["converter_frame"], rel=1e-3
    )
    assert report["synth_fps"] == pytest.approx(1000.0 / t["synth_frame"], rel=1e-3)
    assert report["train_nchw_over_nhwc"] == pytest.approx(t["train_step_nchw"] / t["train_step_nhwc"], rel=1e-3)
    assert report["node_refined_hz"] == pytest.approx(1000.0 / t["node_refined_stream_every1"], rel=1e-3)


def test_refinement_figures_measure_refined_frames(report):
    """The shipped model and map on consecutive campus frames: most frames refined, and refining costs time."""
    t = report["times_ms"]
    assert report["refine_share_every1"] >= 0.5 and report["refine_share_every2"] >= 0.5, report
    assert t["refine_step_every1"] > t["refine_step_none"], t
    assert "node lockstep" in format_table(report) and "every 2nd frame" in format_table(report)
    assert t["node_refined_stream_every1"] > 0 and t["node_refined_latency_every1"] > 0, t
    assert report["node_refine_share_every1"] >= 0.5, report  # the node's own diagnostics after the stream


def test_quick_run_says_what_it_measured(report):
    assert report["quick"] is True and report["paper_input_size"] == [224, 128]
    assert any(n.startswith("quick:") for n in report["notes"])
    assert report["lite_input_size"] == [224, 128] and report["camera_size"] == [640, 360]
    assert report["machine"]["torch_threads"] == 1 and report["settings"]["converter_frames"] == 12
    assert report["converter_frames"] == 12 and report["converter_bag_mb"] > 0
    assert (
        50 < report["peak_rss_mb"] < 100_000 and report["node_rss_mb"] <= report["peak_rss_mb"]
    )  # a node with torch loaded
    table = format_table(report)
    for name in TARGETS:
        assert name in table
    assert "load average" in table and "note: quick" in table


def test_soak_figures_come_from_the_soak_files(report):
    """The node fed at 15 Hz with depth and bad messages for SOAK_MINUTES: the figures are those of its soak.json,
    and its table and plot are written."""
    soak = report["soak"]
    raw = json.loads((Path(soak["plot"]).parent / "soak.json").read_text())
    assert raw["good_frames_sent"] == soak["good_frames_sent"] >= 0.5 * 15 * 60 * SOAK_MINUTES
    assert 0 < soak["answered"] == raw["answered"] <= soak["good_frames_sent"] and soak["bad_messages_sent"] > 0
    assert report["soak_answered_share"] == pytest.approx(soak["answered"] / soak["good_frames_sent"])
    assert report["soak_latency_p99_ms"] == raw["latency_ms_p99"] >= raw["latency_ms_p50"] > 0
    assert report["soak_rss_growth_mb"] >= 0 and Path(soak["plot"]).stat().st_size > 0
    assert (Path(soak["plot"]).parent / "soak.md").read_text().startswith("| figure | value |")
    assert f"{soak['answered']} of {soak['good_frames_sent']} good frames answered" in format_table(report)


def test_resnet50_is_the_standard_one():
    """25.6 M parameters and 9.34 GMAC at 448x256, as torchvision's resnet50 (the yardstick of docs/performance.md)."""
    with single_thread():
        model = ResNet50().eval()
        assert sum(p.numel() for p in model.parameters()) == 25_557_032
        counter = FlopCounterMode(display=False)
        with counter, torch.inference_mode():
            assert model(torch.zeros(1, 3, 256, 448)).shape == (1, 1000)
    assert counter.get_total_flops() / 2e9 == pytest.approx(9.34, abs=0.01)


def test_interleaved_rotates_the_order_and_cleans_up_untimed():
    calls, cleaned = [], []
    times = interleaved(
        {"a": lambda: calls.append("a"), "b": lambda: calls.append("b"), "c": lambda: calls.append("c")},
        repetitions=3,
        warmup=1,
        after=cleaned.append,
    )
    assert calls == [
        "a",
        "b",
        "c",
        "a",
        "b",
        "c",
        "b",
        "c",
        "a",
        "c",
        "a",
        "b",
    ]  # warm-up, then each round starts elsewhere
    assert cleaned == calls and all(len(v) == 3 and min(v) >= 0 for v in times.values())


def test_bad_settings_are_one_line_errors(tmp_path, capsys):
    cfg = tmp_path / "b.yaml"
    for text, expected in (
        ("repetition: 3\n", "unknown bench setting"),
        ("camera_size: [640]\n", "camera_size"),
        ("threads: -1\n", "threads"),
        ("node_backend: trt\n", "node_backend"),
        ("[1, 2]\n", "mapping"),
    ):
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


def test_parts_that_are_not_installed_are_reported_not_measured(tmp_path):
    """As on a GPU machine with PyTorch only: without rclpy, rosbags and onnx the bench still measures
    the network figures and says, per figure, what was not measured and why (a real run in a fresh
    interpreter in which importing those packages fails)."""
    (tmp_path / "b.yaml").write_text(
        "threads: 1\nrepetitions: 1\nwarmup: 0\npaper_input_size: [128, 64]\nsynth_frames: 2\n"
    )
    code = (
        "import sys\nsys.modules.update(rclpy=None, rosbags=None, onnx=None)\nfrom vlocnetpp_core.cli import main\n"
        f"sys.exit(main(['bench', '--quick', '--json', '--config', {str(tmp_path / 'b.yaml')!r}]))"
    )
    env = dict(os.environ, VLOCNETPP_CACHE=str(tmp_path / "cache"))
    proc = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads(proc.stdout)
    for name in ("node_latency_over_step", "converter_speed_over_png_decode", "peak_rss_mb"):
        assert report[name] is None and report["targets"][name]["met"] is None
    assert report["lite_hz_onnx"] is None and report["mtl_step_over_resnet50_onnx"] is None
    assert report["lite_backend"] == report["paper_backend"] == "torch"
    for name in ("cached_vs_recompute_speedup", "mtl_step_over_resnet50", "lite_hz", "synth_fps", "paper_step_ms"):
        assert report[name] > 0
    notes = "\n".join(report["notes"])
    assert "node not measured" in notes and "'rclpy'" in notes
    assert "converter not measured" in notes and "'rosbags'" in notes
    assert "onnx backend not measured" in notes and "'onnx'" in notes
    assert "not measured" in format_table(report)


def _small_paper_model(device: str) -> tuple[VLocNetPP, torch.Tensor, torch.Tensor]:
    """The paper config at 128x64 on ``device``, a random frame and plausible intrinsics."""
    import dataclasses

    cfg = dataclasses.replace(load_model_config("paper"), input_size=(128, 64))
    torch.manual_seed(0)
    model = VLocNetPP(cfg).eval().to(device)
    W, H = cfg.input_size
    K = torch.tensor([[[0.55 * W, 0.0, (W - 1) / 2], [0.0, 0.55 * W, (H - 1) / 2], [0.0, 0.0, 1.0]]], device=device)
    return model, torch.rand(1, 3, H, W, device=device), K


def test_streaming_step_needs_no_host_values():
    """What a CUDA graph needs of the step (bench/cuda_graph.py): it runs on the meta device (tensors
    without data), so it reads no value back to the host (no .item(), nonzero or data-dependent
    branch) and creates no tensor on the CPU behind the caller's back (mixing devices raises)."""
    model, image, K = _small_paper_model("cpu")
    model = model.to("meta")
    image, K = image.to("meta"), K.to("meta")
    with torch.inference_mode():
        _, state = model.step(image, None, K)
        out, new = model.step(image, state, K)
    assert out.seg_logits.device.type == "meta" and out.seg_logits.shape == (1, 10, 64, 128)
    assert new.sem_res5c.device.type == "meta" and out.xyz.shape == (1, 3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
def test_cuda_graph_step_matches_the_eager_step_over_a_stream():
    model, image, K = _small_paper_model("cuda")
    with torch.inference_mode():
        _, state = model.step(image, None, K)
        graph_step = CudaGraphStep(model, image, state, K)
        eager_state, graph_state = state, state
        for k in range(3):
            frame = torch.rand_like(image)
            eager, eager_state = model.step(frame, eager_state, K)
            captured, graph_state = graph_step(frame, graph_state, K)
            for head in (
                "xyz",
                "quat",
                "rel_xyz",
                "rel_quat",
                "seg_logits",
            ):  # untrained weights: large logits, so relative
                torch.testing.assert_close(
                    getattr(captured, head), getattr(eager, head), rtol=1e-4, atol=1e-4, msg=f"frame {k} {head}"
                )
