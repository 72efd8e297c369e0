"""The PyTorch backend gives the numpy backend's results (here on torch's CPU build)."""

import dataclasses
import sys

import numpy as np
import pytest

from mf_lpr_ros.core.backends import resolve_backend
from mf_lpr_ros.core.descriptor import describe_points
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.core.matched_filter import LocalCorrelation, SpectralBank, correlate_fft2
from mf_lpr_ros.core.prefilter import PolarSpectrumIndex
from mf_lpr_ros.core.search import MatchedFilterIndex
from mf_lpr_ros.errors import ConfigError
from mf_lpr_ros.params import DescriptorParams, SearchParams
from mf_lpr_ros.sim.synthetic import scan_world

torch_backend = pytest.importorskip("mf_lpr_ros.core.backends.torch_backend",
                                    reason="PyTorch is not installed (make test installs it)")
PARAMS = DescriptorParams(voxel_size=0.4, z_min=-1.2)


def test_bank_operations_match_numpy():
    rng = np.random.default_rng(0)
    references = (rng.random((11, 20, 20)) < 0.3).astype(np.float32) - 0.15
    queries = (rng.random((3, 20, 20)) < 0.3).astype(np.float32) - 0.15
    cpu, gpu = SpectralBank(20, 20, 4, capacity=2), torch_backend.TorchSpectralBank(20, 20, 4, 2)
    for bank in (cpu, gpu):
        bank.append(references[:5])
        bank.append(references[5:])
    cpu_prepared, gpu_prepared = cpu.prepare_queries(queries), gpu.prepare_queries(queries)
    everything = np.arange(11)
    np.testing.assert_allclose(gpu.best_of_subset(gpu_prepared, everything, chunk_size=4)[0],
                               cpu.best_of_subset(cpu_prepared, everything, chunk_size=4)[0],
                               atol=1e-4)
    subset = np.array([9, 2, 5])
    (cpu_best, cpu_volume), (gpu_best, gpu_volume) = (cpu.best_of_subset(cpu_prepared, subset),
                                                      gpu.best_of_subset(gpu_prepared, subset))
    np.testing.assert_allclose(gpu_best, cpu_best, atol=1e-4)
    np.testing.assert_allclose(gpu.peaks(gpu_volume, [1, 2]), cpu.peaks(cpu_volume, [1, 2]),
                               atol=1e-4)
    np.testing.assert_allclose(gpu.locate(gpu_prepared, subset),
                               cpu.locate(cpu_prepared, subset), atol=1e-4)
    allowed = np.array([[True, False, True], [False, False, True], [True, True, False]])
    (cpu_best, cpu_volume), (gpu_best, gpu_volume) = (
        cpu.best_of_subset(cpu_prepared, subset, allowed=allowed),
        gpu.best_of_subset(gpu_prepared, subset, allowed=allowed))
    np.testing.assert_allclose(gpu_best, cpu_best, atol=1e-4)
    np.testing.assert_allclose(gpu.peaks(gpu_volume, [0, 2]), cpu.peaks(cpu_volume, [0, 2]),
                               atol=1e-4)
    np.testing.assert_allclose(gpu.locate(gpu_prepared, subset, allowed),
                               cpu.locate(cpu_prepared, subset, allowed), atol=1e-4)
    np.testing.assert_allclose(gpu.norms, cpu.norms)
    correlation = torch_backend.TorchLocalCorrelation(references.shape[1:], 4)
    np.testing.assert_allclose(
        correlation.correlate(correlation.spectra(queries), correlation.spectra(references[3:4])),
        correlate_fft2(queries, references[3], 4), atol=1e-4)
    query_spectra = correlation.spectra(queries)
    np.testing.assert_allclose(
        correlation.correlate_pairs([query_spectra[0], query_spectra[1]],
                                    correlation.spectra(references[2:4]), np.array([1, 0])),
        np.stack([correlate_fft2(queries[0:1], references[3], 4)[0],
                  correlate_fft2(queries[1:2], references[2], 4)[0]]), atol=1e-4)
    sharpened = torch_backend.TorchLocalCorrelation(references.shape[1:], 4, sharpening=0.125)
    on_host = LocalCorrelation(references.shape[1:], 4, sharpening=0.125)
    np.testing.assert_allclose(
        sharpened.correlate(sharpened.spectra(queries),
                            sharpened.reference_spectra(references[3:4])),
        on_host.correlate(on_host.spectra(queries), on_host.reference_spectra(references[3:4])),
        atol=1e-4)


def test_prefilter_matches_numpy():
    images = np.random.default_rng(1).random((7, 60, 60)).astype(np.float32)
    cpu, gpu = PolarSpectrumIndex(60, capacity=2), torch_backend.TorchPolarSpectrumIndex(60, 2)
    for index in (cpu, gpu):
        index.append(images[:3])
        index.append(images[3:])
    np.testing.assert_allclose(gpu.scores(images[4], stop=6), cpu.scores(images[4], stop=6),
                               atol=1e-5)
    # Angles between bins come from the correlations' values: equal to float32 rounding,
    # modulo half a turn.
    for gpu_angles, cpu_angles in ((gpu.angles(images[4], np.array([4, 1])),
                                    cpu.angles(images[4], np.array([4, 1]))),
                                   (gpu.angles_between(4, np.array([0, 1])),
                                    cpu.angles_between(4, np.array([0, 1])))):
        difference = (gpu_angles - cpu_angles + 90.0) % 180.0 - 90.0
        np.testing.assert_allclose(difference, 0.0, atol=1e-3)


def test_search_results_match_numpy(world, tmp_path):
    rng = np.random.default_rng(0)
    reference_map = ReferenceMap(PARAMS)
    for i, (x, y, yaw) in enumerate([(0, 0, 0.0), (25, 0, 1.0), (0, 25, -2.0), (20, 20, 0.3)]):
        points, pose = scan_world(world, x, y, yaw, rng)
        reference_map.append(describe_points(points, PARAMS, reference=True, seed_key=i), pose,
                             float(i), i)
    reference_map.save(tmp_path / "four.mfmap")
    statuses = []
    for top_k, spectra, window in ((0, "memory", 0.0), (2, "memory", 10.0),
                                   (2, "on_demand", 0.0), (2, "on_demand", 10.0)):
        search = SearchParams(prefilter_top_k=top_k, backend="numpy", reference_spectra=spectra,
                              global_yaw_window_deg=window)
        cpu = MatchedFilterIndex(reference_map, search)
        # On demand from a file: the first start writes the prefilter cache, the second
        # adopts it on the device.
        gpu = MatchedFilterIndex(ReferenceMap.load(tmp_path / "four.mfmap"),
                                 dataclasses.replace(search, backend="torch"))
        assert gpu.backend == "torch" and cpu.backend == "numpy"
        statuses.append(gpu.prefilter_cache_status)
        for truth in ((1.3, -0.7, 0.5), (21.45, 18.2, -1.7)):
            points, _ = scan_world(world, *truth, np.random.default_rng(1))
            occupancy = describe_points(points, PARAMS)
            expected, got = cpu.query(occupancy), gpu.query(occupancy)
            assert got.reference_index == expected.reference_index
            assert list(got.candidates) == list(expected.candidates)
            np.testing.assert_allclose(got.pose, expected.pose, atol=1e-4)
            assert got.confidence == pytest.approx(expected.confidence, abs=1e-5)
            np.testing.assert_allclose(got.covariance, expected.covariance, rtol=1e-3, atol=1e-9)
    assert "cached at" in statuses[2] and statuses[3].startswith("loaded from")


def test_backend_choice(monkeypatch):
    monkeypatch.setattr(torch_backend, "cuda_available", lambda: False)
    assert resolve_backend("auto") == "numpy"
    assert resolve_backend("torch") == "torch"
    monkeypatch.setattr(torch_backend, "cuda_available", lambda: True)
    assert resolve_backend("auto") == "torch"
    assert resolve_backend("numpy") == "numpy"


def test_torch_backend_without_pytorch_names_the_problem(monkeypatch):
    monkeypatch.delitem(sys.modules, "mf_lpr_ros.core.backends.torch_backend")
    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(ConfigError, match="backend is 'torch' but PyTorch cannot be imported"):
        resolve_backend("torch")
    assert resolve_backend("auto") == "numpy"
