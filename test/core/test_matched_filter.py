import numpy as np
import pytest
from scipy import ndimage

from mf_lpr_ros.core.matched_filter import (
    LocalCorrelation,
    SpectralBank,
    correlate_fft2,
    detail_emphasis,
)
from mf_lpr_ros.core.workers import Workers


def correlate_direct(query, reference, max_shift):
    """The definition S(di, dj) = sum Q(i, j) R(i + di, j + dj), shift by shift."""
    height, width = reference.shape
    n_shifts = 2 * max_shift + 1
    scores = np.zeros((n_shifts, n_shifts))
    for di in range(-max_shift, max_shift + 1):
        for dj in range(-max_shift, max_shift + 1):
            q_rows = slice(max(0, -di), min(height, height - di))
            q_cols = slice(max(0, -dj), min(width, width - dj))
            r_rows = slice(q_rows.start + di, q_rows.stop + di)
            r_cols = slice(q_cols.start + dj, q_cols.stop + dj)
            scores[di + max_shift, dj + max_shift] = np.sum(
                query[q_rows, q_cols].astype(np.float64) * reference[r_rows, r_cols])
    return scores


@pytest.mark.parametrize("size,max_shift", [(12, 4), (16, 15), (20, 3)])
def test_bank_equals_direct_correlation(rng, size, max_shift):
    references = rng.normal(size=(7, size, size)).astype(np.float32)
    queries = rng.normal(size=(3, size, size)).astype(np.float32)
    bank = SpectralBank(size, size, max_shift, capacity=2)
    bank.append(references[:3])
    bank.append(references[3:])  # growing past capacity keeps earlier references
    prepared = bank.prepare_queries(queries)
    volume = bank.correlate_subset(prepared, np.arange(7))
    for r in range(7):
        for a in range(3):
            direct = correlate_direct(queries[a], references[r], max_shift)
            np.testing.assert_allclose(volume[:, a, :, r].T, direct, atol=1e-3)
            np.testing.assert_allclose(correlate_fft2(queries[a:a + 1], references[r],
                                                      max_shift)[0],
                                       direct, atol=1e-3)


@pytest.mark.parametrize("size,max_shift", [(12, 4), (15, 3), (10, 9)])
def test_allowed_pairs_score_as_the_direct_correlation_at_any_size(rng, size, max_shift):
    references = rng.normal(size=(6, size, size)).astype(np.float32)
    queries = rng.normal(size=(4, size, size)).astype(np.float32)
    bank = SpectralBank(size, size, max_shift, capacity=2)
    bank.append(references[:2])
    bank.append(references[2:])  # growing past capacity keeps earlier references
    subset = np.array([5, 0, 3, 1])
    allowed = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 1], [0, 0, 0, 1]], dtype=bool)
    best, pairs = bank.best_of_subset(bank.prepare_queries(queries), subset, allowed=allowed)
    for p, (k, a) in enumerate(zip(pairs.positions, pairs.queries)):
        np.testing.assert_allclose(pairs.scores[p],
                                   correlate_direct(queries[a], references[subset[k]], max_shift),
                                   atol=1e-3)
    expected = [max(correlate_direct(queries[a], references[r], max_shift).max()
                    for a in np.flatnonzero(allowed[k])) for k, r in enumerate(subset)]
    np.testing.assert_allclose(best, expected, atol=1e-3)
    np.testing.assert_allclose(bank.norms, np.linalg.norm(references, axis=(1, 2)), rtol=1e-5)
    bank.refill(references[4:])
    assert len(bank) == 2
    best, _ = bank.best_of_subset(bank.prepare_queries(queries), np.array([1]),
                                  allowed=np.array([[0, 0, 1, 0]], dtype=bool))
    np.testing.assert_allclose(best, [correlate_direct(queries[2], references[5],
                                                       max_shift).max()], atol=1e-3)


MAX_SHIFT = 5


def random_bank(rng, size=14):
    """A bank of 9 random references and 4 random queries, prepared."""
    references = (rng.random((9, size, size)) < 0.3).astype(np.float32) - 0.15
    queries = (rng.random((4, size, size)) < 0.3).astype(np.float32) - 0.15
    bank = SpectralBank(size, size, MAX_SHIFT)
    bank.append(references)
    return bank, references, queries, bank.prepare_queries(queries)


def test_global_best_and_location_match_brute_force(rng):
    max_shift = MAX_SHIFT
    bank, references, queries, prepared = random_bank(rng)
    best, _ = bank.best_of_subset(prepared, np.arange(9), chunk_size=4)
    brute = np.array([[correlate_direct(q, r, max_shift) for q in queries] for r in references])
    np.testing.assert_allclose(best, brute.reshape(9, -1).max(axis=1), atol=1e-3)
    top = int(np.argmax(best))
    assert top == int(np.argmax(brute.reshape(9, -1).max(axis=1)))
    located = bank.locate(prepared, np.array([top, 2]))
    for row, reference in zip(located, (top, 2)):
        a, di, dj, score = row
        expected = np.unravel_index(np.argmax(brute[reference]), brute[reference].shape)
        assert (a, di + max_shift, dj + max_shift) == tuple(int(v) for v in expected)
        assert score == pytest.approx(brute[reference].max(), abs=1e-3)
    # Any subset, in any order, scores as the full search does.
    subset = np.array([7, 0, 4, 8])
    for chunk_size in (3, 4):
        subset_best, volume = bank.best_of_subset(prepared, subset, chunk_size=chunk_size)
        np.testing.assert_allclose(subset_best, best[subset], atol=1e-5)
    # One chunk: the volume comes back and locates as a second pass would.
    np.testing.assert_allclose(bank.peaks(volume, [2, 0]), bank.locate(prepared, subset[[2, 0]]),
                               atol=1e-5)


def test_shifted_copy_peaks_at_its_shift(rng):
    image = rng.normal(size=(30, 30)).astype(np.float32)
    reference = np.zeros_like(image)
    reference[5:, :27] = image[:25, 3:]  # content moved down 5 rows, left 3 columns
    surface = correlate_fft2(image[None], reference, 8)[0]
    row, col = np.unravel_index(np.argmax(surface), surface.shape)
    assert (row - 8, col - 8) == (5, -3)


def test_query_spectra_serve_several_references_and_batches(rng):
    references = rng.normal(size=(2, 30, 30)).astype(np.float32)
    queries = rng.normal(size=(5, 30, 30)).astype(np.float32)
    correlation = LocalCorrelation((30, 30), 6)
    spectra = correlation.spectra(queries)
    reference_spectra = correlation.spectra(references)
    for r, reference in enumerate(references):
        for batch in ([0, 1], [2, 3, 4], [4, 0]):
            np.testing.assert_allclose(
                correlation.correlate(spectra[batch], reference_spectra[r: r + 1]),
                correlate_fft2(queries[batch], reference, 6), atol=1e-5)
    # Pair by pair: query k against reference k % 2, in one batch, as the same product.
    pairs = correlation.correlate(spectra, reference_spectra[np.arange(5) % 2])
    for k in range(5):
        np.testing.assert_allclose(pairs[k], correlate_fft2(queries[k: k + 1],
                                                            references[k % 2], 6)[0], atol=1e-5)
    order = [4, 0, 3, 3, 1]
    np.testing.assert_array_equal(
        correlation.correlate_pairs([spectra[k] for k in order], reference_spectra,
                                    np.array([1, 0, 0, 1, 1])),
        correlation.correlate(spectra[order], reference_spectra[[1, 0, 0, 1, 1]]))
    np.testing.assert_allclose(
        correlation.correlate_pairs([spectra[2]], reference_spectra, np.array([1]))[0],
        correlate_fft2(queries[2:3], references[1], 6)[0], atol=1e-5)


def test_a_sharpened_reference_is_the_reference_convolved_with_the_kernel(rng):
    # Zero border, as the local stage's images have beyond their window: the FFT's padding
    # then holds the whole convolution.
    reference = np.zeros((30, 30), dtype=np.float32)
    reference[2:-2, 2:-2] = rng.normal(size=(26, 26))
    queries = rng.normal(size=(3, 30, 30)).astype(np.float32)
    s = 0.125
    kernel = np.array([-s, 1 + 2 * s, -s])
    sharpened = ndimage.convolve(ndimage.convolve(reference, kernel[None, :], mode="constant"),
                                 kernel[:, None], mode="constant")
    correlation = LocalCorrelation((30, 30), 6, sharpening=s)
    np.testing.assert_allclose(
        correlation.correlate(correlation.spectra(queries),
                              correlation.reference_spectra(reference[None])),
        correlate_fft2(queries, sharpened, 6), atol=1e-4)
    # Off, a reference is correlated as it is.
    plain = LocalCorrelation((30, 30), 6)
    np.testing.assert_array_equal(plain.reference_spectra(reference[None]),
                                  plain.spectra(reference[None]))


def test_detail_emphasis_keeps_the_mean_and_raises_the_finest_detail():
    emphasis = detail_emphasis((8, 8), 0.125)
    assert emphasis.shape == (8, 5)
    assert emphasis[0, 0] == pytest.approx(1.0)
    # The finest detail along both axes: (1 + 4s)^2.
    assert emphasis[4, 4] == pytest.approx(1.5 ** 2)
    assert np.all(np.diff(emphasis[0, :]) > 0)


def test_a_bank_on_two_threads_scores_as_on_one(rng):
    references = rng.normal(size=(40, 24, 24)).astype(np.float32)
    queries = rng.normal(size=(6, 24, 24)).astype(np.float32)
    subset = np.arange(0, 40, 3)
    allowed = rng.random((len(subset), len(queries))) < 0.5
    results = []
    for threads in (1, 2):
        bank = SpectralBank(24, 24, 5, workers=Workers(threads))
        bank.append(references)
        prepared = bank.prepare_queries(queries)
        best, pairs = bank.best_of_subset(prepared, subset, allowed=allowed)
        results.append((best, pairs.scores,
                        bank.best_of_subset(bank.prepare_queries(queries), np.arange(40))[0]))
    for one, two in zip(*results):
        np.testing.assert_allclose(two, one, rtol=1e-5, atol=1e-5)


def test_allowed_pairs_score_as_the_full_search_and_the_others_not_at_all(rng):
    bank, _, queries, prepared = random_bank(rng)
    subset = np.array([7, 0, 4, 8, 2])
    allowed = rng.random((len(subset), len(queries))) < 0.5
    allowed[3] = False          # a reference with no pair allowed scores -inf
    allowed[:, 1] = False       # a query no reference may pair with is never correlated
    allowed[0, 0] = allowed[2, 2] = True
    full = bank.correlate_subset(prepared, subset)
    best, pairs = bank.best_of_subset(prepared, subset, allowed=allowed)
    # Exactly the allowed pairs were computed, each scoring as in the full search.
    assert sorted(zip(pairs.positions, pairs.queries)) == sorted(zip(*np.nonzero(allowed)))
    for p, (k, a) in enumerate(zip(pairs.positions, pairs.queries)):
        np.testing.assert_allclose(pairs.scores[p], full[:, a, :, k].T, atol=1e-4)
    for k in range(len(subset)):
        expected = full[:, allowed[k], :, k].max() if allowed[k].any() else -np.inf
        assert best[k] == pytest.approx(expected, abs=1e-4)
    # Located only among the allowed pairs, whether from the pairs or a second pass, at the
    # full search's best allowed alignment.
    located = bank.locate(prepared, subset[[0, 2]], allowed[[0, 2]])
    np.testing.assert_allclose(located, bank.peaks(pairs, [0, 2]), atol=1e-4)
    for row, k in zip(located, (0, 2)):
        masked = np.where(allowed[k][None, :, None], full[:, :, :, k], -np.inf)
        dj, a, di = np.unravel_index(np.argmax(masked), masked.shape)
        assert tuple(int(v) for v in row[:3]) == (a, di - MAX_SHIFT, dj - MAX_SHIFT)
        assert row[3] == pytest.approx(masked.max(), abs=1e-4)
    # Chunked, the same best scores; a chunk with no pair allowed computes nothing.
    chunked, _ = bank.best_of_subset(prepared, subset, chunk_size=2, allowed=allowed)
    np.testing.assert_allclose(chunked, best)
    nothing, pairs = bank.best_of_subset(prepared, subset[3:4], allowed=allowed[3:4])
    assert nothing[0] == -np.inf and len(pairs.positions) == 0


def test_allowed_pairs_score_alike_from_candidate_spectra_made_beforehand(rng):
    bank, _, queries, _ = random_bank(rng)
    subset = np.array([7, 0, 4, 8, 2])
    allowed = rng.random((len(subset), len(queries))) < 0.5
    allowed[:, 0] = True
    made_here = bank.best_of_subset(bank.prepare_queries(queries), subset, allowed=allowed)
    candidates = bank.candidate_spectra(subset)
    assert candidates.shape == (len(subset), bank.column_length, bank.n_freqs)
    for chunk_size in (256, 2):
        # Sliced per chunk: reference k's spectra stay with reference k.
        prepared = bank.prepare_queries(queries, pairs=True)
        assert prepared.plane_spectra is not None
        best, pairs = bank.best_of_subset(prepared, subset, chunk_size, allowed, candidates)
        # Equal to float32 rounding: a chunk's matrix products may take another BLAS kernel
        # for another shape, and sum in another order (bit for bit on some CPUs, not all).
        np.testing.assert_allclose(best, made_here[0], rtol=1e-6)
    np.testing.assert_allclose(
        bank.best_of_subset(bank.prepare_queries(queries), subset, 256, allowed,
                            candidates)[1].scores, made_here[1].scores, rtol=1e-6, atol=1e-6)
    # Another reference's spectra in its place change its scores: they are what is used.
    swapped = candidates[[1, 0, 2, 3, 4]]
    moved, _ = bank.best_of_subset(bank.prepare_queries(queries), subset, 256, allowed, swapped)
    assert not np.allclose(moved[:2], made_here[0][:2])


def test_candidate_spectra_are_made_once_and_follow_the_references_they_belong_to(rng):
    size, max_shift = 12, 4
    references = rng.normal(size=(7, size, size)).astype(np.float32)
    kept = SpectralBank(size, size, max_shift, capacity=2)
    made_each_time = SpectralBank(size, size, max_shift, capacity=2)
    made_each_time.kept_plane_spectra_bytes = 0
    transformed = []
    transform = kept._transformed_along_y
    kept._transformed_along_y = lambda references: (transformed.append(references.tolist())
                                                    or transform(references))

    def fill(images: np.ndarray, how: str) -> None:
        for bank in (kept, made_each_time):
            getattr(bank, how)(images)

    def assert_alike(subset: list[int]) -> None:
        np.testing.assert_array_equal(kept.candidate_spectra(np.array(subset)),
                                      made_each_time.candidate_spectra(np.array(subset)))

    fill(references[:3], "append")
    # Their room is taken with the references, before any search (a localiser's memory is
    # settled once its map is loaded); each reference is transformed once, when first asked for.
    assert kept.nbytes > made_each_time.nbytes and not transformed
    assert_alike([2, 0])
    assert_alike([0, 1, 2])
    assert transformed == [[2, 0], [1]]
    # Grown past its room, the bank keeps its references and makes their spectra again.
    fill(references[3:5], "append")
    assert_alike([4, 0, 3])
    assert transformed[-1] == [4, 0, 3]
    # Where every reference's would not fit, none is kept.
    kept.kept_plane_spectra_bytes = 0
    for _ in range(2):
        assert_alike([1, 0])
        assert transformed[-1] == [1, 0]
    assert len(transformed) == 5
    assert kept.nbytes == made_each_time.nbytes
    # Refilled (each query's candidates), every reference is another image and none is kept.
    kept.kept_plane_spectra_bytes = made_each_time.kept_plane_spectra_bytes = 2 ** 20
    fill(references[5:], "refill")
    for _ in range(2):
        assert_alike([1, 0])
        assert transformed[-1] == [1, 0]
    assert len(transformed) == 7
    assert kept.nbytes == made_each_time.nbytes


@pytest.mark.parametrize("size,max_shift", [(14, 4), (15, 6), (60, 10)])
def test_a_quarter_turned_spectrum_is_the_spectrum_of_the_turned_image(rng, size, max_shift):
    bank = SpectralBank(size, size, max_shift)
    images = rng.standard_normal((3, size, size)).astype(np.float32)
    spectra = bank.prepare_queries(images, pairs=True).plane_spectra
    for turns in (1, 2, 3, 4, -1):
        turned = np.rot90(images, -turns, axes=(1, 2))
        np.testing.assert_allclose(bank.quarter_turned(spectra, turns),
                                   bank.prepare_queries(turned, pairs=True).plane_spectra,
                                   rtol=0, atol=1e-5 * np.abs(spectra).max())
    with pytest.raises(ValueError, match="square"):
        SpectralBank(size, size + 2, max_shift).quarter_turned(spectra, 1)


def test_queries_laid_out_from_their_quarter_turns_score_as_those_transformed(rng):
    bank, references, queries, _ = random_bank(rng)
    turned = np.concatenate([queries[:2], np.rot90(queries[:2], -1, axes=(1, 2)),
                             np.rot90(queries[:1], -2, axes=(1, 2)),
                             np.rot90(queries[1:2], -3, axes=(1, 2)), queries[2:]])
    turned_from = np.array([[-1, 0], [-1, 0], [0, 1], [1, 1], [0, 2], [1, 3], [-1, 0],
                            [-1, 0]])
    subset = np.arange(len(references))
    allowed = rng.random((len(subset), len(turned))) < 0.6
    allowed[:, 0] = True
    transformed = bank.best_of_subset(bank.prepare_queries(turned, pairs=True), subset,
                                      allowed=allowed)
    laid_out = bank.best_of_subset(bank.prepare_queries(turned, pairs=True,
                                                        turned_from=turned_from),
                                   subset, allowed=allowed)
    np.testing.assert_allclose(laid_out[0], transformed[0], rtol=1e-5)
    np.testing.assert_allclose(laid_out[1].scores, transformed[1].scores, rtol=1e-5, atol=1e-5)
    # Laid out from the wrong image, the scores are another query's.
    wrong = turned_from.copy()
    wrong[2] = (1, 1)
    misplaced = bank.best_of_subset(bank.prepare_queries(turned, pairs=True,
                                                         turned_from=wrong),
                                    subset, allowed=allowed)
    assert not np.allclose(misplaced[1].scores, transformed[1].scores, atol=1e-3)
