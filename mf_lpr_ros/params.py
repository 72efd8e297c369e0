"""The descriptor's and the search's parameters, validated on construction.

Every default below is the paper's value (docs/METHOD.md section 4) unless a comment says why not.
mf_lpr_ros.config groups them with the map spacing into a Config and loads them from YAML.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from mf_lpr_ros.errors import ConfigError


@dataclass(frozen=True)
class DescriptorParams:
    """How a scan becomes a BEV occupancy descriptor (docs/METHOD.md section 1).

    size: cells per side of the high-resolution grid (D).
    voxel_size: cell and voxel edge in metres (v).
    z_min, z_max: height band kept, metres in the sensor frame (None = unbounded).
    max_range: horizontal range cut in metres (None = only the square crop).
    density_mode: "voxels" counts occupied voxels per column (paper), "points" counts raw
        points per column (the authors' scripts).
    density_threshold: a column is occupied when its density exceeds this (d).
    unoccupied_weight: value of unoccupied cells (w).
    patch_size, patch_cap: reference scans keep at most patch_cap occupied cells in each
        patch_size x patch_size patch (m, c).
    pool: average-pooling factor for the low-resolution descriptor (u).
    seed: base of the per-scan random generator used by the patch cap.
    level: remove the scan's roll and pitch (from its pose or an IMU orientation) before
        building the descriptor; for handheld or tilted sensors.
    crop: "square" (paper) keeps the whole size x size window; "disc" keeps its inscribed disc
        (radius size * voxel_size / 2) and gives the cells outside it weight 0 rather than w,
        so that a scan and the same scan turned by any yaw cover the same ground: the
        square's corners hold different parts of the scene at different headings.
    field_of_view_deg, heading_deg: the sensor's horizontal field of view, centred on
        heading_deg (0 = +x, counter-clockwise). Below 360 the footprint is that wedge of the
        window, and the cells outside it weigh 0: a forward-looking sensor (a Livox Avia sees
        ~70 deg) has not seen them, they are not free space. The query's wedge turns with it
        in the search, and rotations wider than the field of view (no common ground) are not
        searched. It raises a match's confidence (the cosine is taken over the wedge), and
        with it false matches': on the HKU Avia keyframes (~80 deg measured) recall is
        unchanged (0.714) and 70-97 closures are published, none false, where 360 publishes
        none, but `auto` with the measured wedge published 142 false closures of 342 on a
        simulated Avia in a town (docs/RESULTS.md, session 61), so it is off by default and
        `auto` does not apply it.
    submap_m: describe each scan together with the earlier scans of the last submap_m metres
        of travel, moved into its sensor frame by odometry (mf_lpr_ros/core/submap.py), for
        sparse or narrow sensors that see too little of a place in one scan. 0 = single scans
        (dense 360-degree sensors). Needs odometry: the source's poses offline, pose_source
        in the nodes; without it, single scans. The map records it, and the localiser uses
        the map's window.
    submap_max_scans, submap_max_age_s: the window also holds at most this many scans and none
        older than this (a robot standing still; a sensor faster than the odometry moves).
    """

    size: int = 120
    voxel_size: float = 0.5
    z_min: float | None = None
    z_max: float | None = None
    max_range: float | None = None
    density_mode: str = "voxels"
    density_threshold: float = 1.0
    unoccupied_weight: float = -0.15
    patch_size: int = 10
    patch_cap: int = 20
    pool: int = 2
    seed: int = 0
    level: bool = False
    crop: str = "disc"
    field_of_view_deg: float = 360.0
    heading_deg: float = 0.0
    submap_m: float = 0.0
    submap_max_scans: int = 100
    submap_max_age_s: float = 60.0

    def __post_init__(self) -> None:
        require_parameter(self.size >= 8 and self.size % 2 == 0, "size", "an even integer >= 8",
                          self.size)
        require_parameter(self.voxel_size > 0, "voxel_size", "> 0", self.voxel_size)
        require_parameter(self.density_mode in ("voxels", "points"), "density_mode",
                          "'voxels' or 'points'",
                 self.density_mode)
        require_parameter(self.density_threshold >= 0, "density_threshold", ">= 0",
                          self.density_threshold)
        require_parameter(-1.0 <= self.unoccupied_weight <= 0.0, "unoccupied_weight", "in [-1, 0]",
                 self.unoccupied_weight)
        require_parameter(self.patch_size >= 1 and self.size % self.patch_size == 0, "patch_size",
                 f"a divisor of size ({self.size})", self.patch_size)
        require_parameter(1 <= self.patch_cap <= self.patch_size ** 2, "patch_cap",
                 f"in [1, patch_size^2 = {self.patch_size ** 2}]", self.patch_cap)
        require_parameter(self.pool >= 1 and self.size % self.pool == 0, "pool",
                 f"a divisor of size ({self.size})", self.pool)
        require_parameter(self.crop in ("square", "disc"), "crop", "'square' or 'disc'", self.crop)
        require_parameter(0 < self.field_of_view_deg <= 360, "field_of_view_deg", "in (0, 360]",
                 self.field_of_view_deg)
        require_parameter(-180 <= self.heading_deg <= 180, "heading_deg", "in [-180, 180]",
                 self.heading_deg)
        if self.z_min is not None and self.z_max is not None:
            require_parameter(self.z_min < self.z_max, "z_min", f"< z_max ({self.z_max})",
                              self.z_min)
        if self.max_range is not None:
            require_parameter(self.max_range > 0, "max_range", "> 0", self.max_range)
        require_parameter(self.submap_m >= 0, "submap_m", ">= 0 (0 = single scans)",
                          self.submap_m)
        require_parameter(self.submap_max_scans >= 1, "submap_max_scans", ">= 1",
                          self.submap_max_scans)
        require_parameter(self.submap_max_age_s > 0, "submap_max_age_s", "> 0",
                          self.submap_max_age_s)

    @property
    def extent_m(self) -> float:
        """Side of the square window covered by the descriptor, in metres."""
        return self.size * self.voxel_size

    @property
    def low_size(self) -> int:
        return self.size // self.pool


@dataclass(frozen=True)
class SearchParams:
    """How a query descriptor is matched against the map (docs/METHOD.md sections 2 and 3).

    rotation_step_deg: rotation sampling of the global stage (k). 5, half the paper's 10: a
        heading up to half a step off the sampled one moves content 24 m out by R * step / 2,
        2.1 m (2.6 low-resolution cells) at 10 and 1.0 m at 5, and the true reference then
        drops out of the finalists. 5 raised every tuning set's recall (rotated KITTI 00 0.987
        -> 0.997, BALM 0.571 -> 0.857 at `handheld`, KITTI 00 closures published 777 -> 805,
        none false: docs/RESULTS.md, session 11) for ~1.7x the query time.
    top_n: distinct references passed from the global to the local stage (n). The paper uses
        2; 3 costs one more local correlation (~2 ms) and lifts retrieval recall@1 on rotated
        KITTI 00 BEV (00_rot, BEVPlace protocol) from 0.985 to 0.991.
    another_place_finalist: the last of the top_n finalists is the best-ranked candidate whose
        global alignment puts the query at another place than the other finalists' (farther
        than rerank_agreement_m, or turned by more than local_rotation_range_deg), not the
        next view of theirs, when it scores within min_distinctiveness of the best: a rival
        that would leave the match indistinct is aligned at full resolution. With references
        2 m apart the top three are often views of one place; when it is a look-alike (a
        street seen the other way round 15 m on), the true place ranked fourth never reached
        the local stage. Not where map_headings is "unknown". Tuning suite 0.8802 -> 0.8822,
        none false, at the same number of local alignments (docs/RESULTS.md, session 36).
    max_shift_m: largest translation between query and reference that is searched, in metres.
        The paper searches every shift of a full linear correlation; a window both bounds
        the cost and rejects alignments with little overlap.
    local_rotation_range_deg, local_rotation_step_deg: the local stage searches rotations
        within +-range of the global best, at this finer step. 6: on every right match of
        sampled KITTI 00 and 00_rot queries the best local angle lay within 4 degrees of the
        global heading (1,324 of 1,325 within 2), and 6 keeps a local step beyond that; 10,
        a margin from the paper's 10-degree global step, gave the same match on every KITTI
        revisit of the tuning suite for 2 more correlations per finalist (docs/RESULTS.md,
        session 30).
    local_sharpening: the local stage correlates the query with each finalist's reference
        sharpened by the kernel [-s, 1 + 2s, -s] along each axis (s = this; 0, the default:
        off): a finalist then scores by where its cells lie more than by the broad mass of
        its structures, which a look-alike shares. The alignment, the ranking of finalists and
        the local distinctiveness follow the sharpened correlation; the confidence stays the
        cosine of the images themselves. 0.125 raised the tuning suite 0.9055 -> 0.9127 and
        the simulated sensors' check (with 0 at 0.3 m cells, where a VLP-16 in a forest lost
        6 of 155 places), but where the localiser verifies without odometry it let 2 of the
        sparse demo world's 141 unseen scans through, and it cost held-out KITTI 02 a query on
        every protocol: off by default (docs/RESULTS.md, session 53).
    score_normalisation: "raw" (paper) ranks by the dot product; "cosine" divides it by the
        reference descriptor's norm so dense references are not favoured.
    min_confidence: matches below this confidence are rejected (the first test of
        mf_lpr_ros/core/verification.py). 0.4 lies between the thresholds that maximise F1 on the
        tuning sets (KITTI 00 BEV: 0.47, BALM handheld: 0.35); the handheld preset uses its
        own. Alone it cannot reach zero false closures on KITTI 00 short of 0.5 (recall 0.70);
        with distinctiveness and odometry consistency it does at 0.4 (recall 0.93).
    min_relative_confidence: a match under min_confidence still passes the confidence test
        when its confidence reaches this fraction of its place's similarity
        (MatchResult.place_similarity: how well the map's own nearest other view of the
        matched place aligns on it). A revisit matches about as well as the map's neighbouring
        views match each other, wherever the sensor and the scene put that level; a look-alike
        mostly matches worse (KITTI 00 every frame: wrong matches under 0.4 reach at most 0.80
        of their places' similarity, 0.64 at the 95th percentile; docs/RESULTS.md, session
        31). Not a guard alone (on a map of one place, the HKU Avia keyframes, wrong matches
        reach it too): distinctiveness and odometry consistency still apply. 0.95, not 0.9:
        both pass the tuning rule, but at 0.9 a run of off-map queries matched 265 m away on
        the 8 m tuning pair stays out by 0.01-0.09 of the ratio (0.81-0.89), at 0.95 by
        0.06-0.14. 0 = off (min_confidence alone).
    chunk_size: references processed per block in the global stage (memory vs. speed).
    prefilter_top_k: the global stage correlates only the k references that a rotation- and
        translation-invariant polar-spectrum ranking puts first (mf_lpr_ros/core/prefilter.py);
        0 searches every reference exhaustively (exact mode). With 64 (and the expansion
        below), the match equals the exhaustive search's on every revisit query of KITTI 00
        BEV (and 00_rot), in ~1/4 of the time at 1500 references and ~1/100 at 20000
        (benchmarks/bench_search.py).
    prefilter_rescore_k: when > prefilter_top_k, the prefilter's best prefilter_rescore_k
        references are ranked again by a coarse matched filter (the low-resolution
        descriptors pooled 2x2 once more, correlated within max_shift_m at the global heading
        nearest each one's prefilter angle and at the opposite one), and its best
        prefilter_top_k go on; 0 (default): the prefilter's own ranking. The polar spectra
        ignore where things lie in the window; the correlation does not. At 256 the candidate
        stage keeps the true place for every query of both KITTI 00 pairs against one
        reference per 8 m (0.994 / 0.988 before) and their recall@1 rises 0.994 -> 0.999 and
        0.962 -> 0.972 (held-out KITTI 02, BEVPlace's protocol: 0.961 -> 0.971), for ~2 ms
        a query (KITTI 00: 10.7 -> 12.7 ms). Not a default: the candidates are then stronger
        look-alikes, which the prefilter's own ranking had kept out. The simulated sparse
        sensor publishes less (handheld at `default` 89 -> 0 closures, `livox` 411 -> 373),
        a grid rendered from the simulator's town relocalises 11 of 14 lanes instead of 14
        (3 matched to a crossing street), and KITTI 02 every frame loses 2 of 316 revisits
        (docs/RESULTS.md, session 29).
    prefilter_retry_top_k, prefilter_retry: when the match found among the prefilter_top_k
        candidates is too weak to accept (confidence under min_confidence), search again over
        the prefilter's best prefilter_retry_top_k (0 or <= prefilter_top_k: never). Where the
        prefilter left the true place out, the match found instead is weak (rotated KITTI 00
        BEV against one reference per 8 m: confidence 0.11-0.16 there, 0.30 and up for every
        right match), so the retry recovers it: retrieval recall@1 there 0.956 -> 0.969, the
        exhaustive search's. prefilter_retry says which searches retry: "requests" only a
        relocalisation request's (a ~/relocalise call waiting for its answer, `mf-lpr
        localise`), where every query is inside the map and an answer may take longer;
        "revisits" (default) a loop-closure stream's too where its weak match contradicts the
        revisit it is on: the confirmed closures in reach (consistency_vouch), carried along
        the odometry, put the scan at a place the map holds (a reference within max_shift_m)
        and none puts it where the weak match does (MatchVerifier.revisit_places). A weak
        match where the revisit puts it is the right place, weakly seen; a revisit carried
        past the mapped route puts the scan where the map cannot answer. KITTI 00 against
        one reference per 8 m: candidate recall 0.994 -> 0.999, recall@1 0.994 -> 0.999;
        tuning suite 0.8962 -> 0.8964, none false, 11 of its queries searched with another
        answer (docs/RESULTS.md, session 42);
        "every_query" every scan of a stream, where most scans revisit nothing and a scan
        from outside the map is weak as well, so the stream pays ~2.5x its time (KITTI 00
        closures 12.5 -> 33.9 ms a query at 256; docs/RESULTS.md, session 16). Without the
        retry a robot standing still where the prefilter misses its place would never be
        relocalised: each of its scans is the same query.
    revisit_check: where a stream's match does not stand on its own (it fails min_confidence
        or distinctiveness) and contradicts the revisit it is on (the places
        prefilter_retry "revisits" reads, MatchVerifier.revisit_places), the reference
        nearest each place the revisit puts the scan is aligned by the local stage at the
        turn that place implies. When its alignment puts the scan at that place (within
        consistency_tolerance_m and _deg) and scores within min_distinctiveness of the
        match, it is reported instead: among alignments the images cannot tell apart, the
        one the odometry predicts. It is reported with distinctiveness 0, so it is
        published only where a confirmed closure vouches for it (consistency_vouch).
        A stream without odometry (no revisit to read) never uses it. Tuning suite 0.9055 ->
        0.9104 (sim_sparse [livox] recall@1 0.937 -> 0.987), sensors suite 0.7512 -> 0.7599,
        none false, no pair lower (docs/RESULTS.md, session 54).
    prefilter_expand_m: the prefilter's 16 best references bring along every reference within
        this distance of them (map positions): the same place seen from a few metres away often
        scores just below them in the exact search, and the prefilter ranks such neighbours
        less consistently. At most prefilter_top_k references are added, the nearest to a
        leader first: along a trajectory that bound is rarely reached (KITTI 00: 30-50 added),
        on a grid rendered 2 m apart it keeps ~450 neighbours from multiplying the search's
        cost. 0 disables.
    reference_spectra: where the global stage's reference spectra live. "memory": every
        reference's, computed when the index is built (~17 KB a reference at the defaults).
        "on_demand": only the prefilter's features are kept (~2.7 KB a reference, cached beside
        the map file by build-map or the map builder node, or else by the first start, so a
        large map starts in seconds), and the candidates' spectra are computed from the map's
        stored occupancy for each query (~5 ms for 100 candidates); needs prefilter_top_k > 0.
        Both give the same matches. "auto" (default): memory up to 50,000 references when the
        index is made, on demand above.
    backend: where the search's array work runs. "numpy" (CPU); "torch" (PyTorch: the CUDA
        GPU when there is one, else torch's CPU build; same matches); "auto" picks torch when
        PyTorch is installed and sees a CUDA device, else numpy.
    threads: threads that share one query's work (numpy backend; torch has its own): the
        global stage's candidate pairs, chunk by chunk, the query's turning and 2-D spectra
        beside the candidates' spectra, and its large products split by columns; numpy and
        scipy's FFTs release the GIL. While a search runs on several threads BLAS is held to
        one thread in the process (core/workers.py says why). 2 on 2 cores: 1,500 generated
        references 12.4 -> 11.1 ms a query (benchmarks/bench_search.py; docs/RESULTS.md,
        session 18); since the candidate pairs are scored from 2-D spectra (session 33),
        against one thread with BLAS held to one as well: 1,500 generated 16.0 -> 15.0 ms,
        KITTI 00 15.3 -> 13.7 ms; the turning beside the candidates' spectra (session 34) took
        KITTI 00's global stage 5.61 -> 4.98 ms. 1 keeps the search on the calling thread (a
        process running several searches at once).
    verify_fitness: geometric verification for the live nodes. When > 0, a match is accepted
        only if ICP (open3d) against the reference's stored cloud finds a correspondence
        within 2 voxels for at least this fraction of the query's points; the ICP-refined pose
        is then published. Needs maps that keep clouds: a map built with a config that
        verifies this way keeps them (as with keep_clouds), and so does loop_closure mode; a
        grid rendered from a global cloud then keeps its site cloud, from which each
        reference's cloud is cut (core.site_cloud). On
        the BALM handheld sequence confidence alone cannot separate true revisits from
        look-alike places (both reach 0.36-0.40); ICP fitness does (true revisits 0.71-0.85 but
        two at 0.64-0.66, look-alikes <= 0.66): the handheld preset uses 0.68. Not a default
        elsewhere: on the HKU Avia keyframes and the held-out Mid-360 campus loop ICP fitness
        accepts wrong places (docs/RESULTS.md, sessions 11 and 12); against a grid's clouds,
        with a 30 m query window of the Avia halves, it refuses all 94 wrong matches
        (fitness <= 0.60) and accepts 126 of 135 right ones (session 25).
    distinct_radius_m: references farther than this from the match count as another place
        when MatchResult.distinctiveness compares the match with the best other place.
    min_distinctiveness: accept a match only when its distinctiveness reaches this (0 = off).
    distinct_aligned_rivals: for a match that passes confidence and would fail
        min_distinctiveness, up to this many of the best-scoring references farther than
        distinct_radius_m are aligned (best first, until one disagrees); one whose alignment
        puts the query within rerank_agreement_m of the match's pose, turned by at most
        local_rotation_range_deg, sees the query's own place from farther along the road,
        the same answer, and is not the other place distinctiveness compares with (0 =
        off). 3: docs/RESULTS.md, session 17; the heading asked since session 55.
    min_local_distinctiveness: a match under min_distinctiveness is distinct all the same when
        its local_distinctiveness (the same comparison at the local stage's resolution,
        MatchResult) reaches this (0 = off). Where the pooled descriptors of a block grid or a
        straight road look alike, the full-resolution alignment still tells the places apart;
        it is held to a larger margin because even a look-alike place differs in detail there.
        0.3: of 0.2-0.4 on the whole tuning suite, the least at which no wrong match passes
        the test by itself (a parallel street on KITTI 00 reaches 0.22-0.28); docs/RESULTS.md,
        session 17.
    consistency_min_support, consistency_window_m, consistency_min_separation_m,
    consistency_tolerance_m, consistency_tolerance_deg: odometry consistency
        (mf_lpr_ros/core/verification.py). When consistency_min_support > 0 and the scans'
        odometry is known, a match is accepted only when at least this many earlier
        candidate matches (those passing the other tests) from the last consistency_window_m of
        travel, each from a query at least consistency_min_separation_m from this one (and at
        least descriptor.submap_m: closer, two submaps share scans, and one wrong match repeats
        in the other), agree with it: the pose one implies, carried along the odometry, lies
        within consistency_tolerance_m and consistency_tolerance_deg of the other's. A false
        match is a one-off; a true revisit repeats along the path. Agreement is symmetric: a
        candidate that lacked support when it came is published, late, once enough later ones
        agree with it (the first matches of a revisit). 0 = off.
    consistency_vouch, consistency_vouch_window_m: a confirmed closure vouches for the matches
        within consistency_vouch_window_m of it on the path, or of the latest match it vouched
        for (its reach runs on along the revisit it anchors), that fail min_confidence or
        min_distinctiveness (or both) and nothing else, or consistency_min_support alone (a
        closure their own agreement helped confirm does not count), and agree with it (as above,
        without the separation): they are published, on time or late. Confidence guards against
        a query that sees too little of the place, distinctiveness against a look-alike place,
        support against a one-off; a match that lands where odometry and an independently
        confirmed closure put the query is none of these. Only confirmed candidates vouch, so
        agreement cannot creep along a road from one vouched match to the next. A weak match
        (under min_confidence) names the place but its weak peak places the query less
        precisely, so it is published where the vouching closures, carried along the odometry,
        put the query (their mean), its alignment to its reference moved to match: published at
        its own pose, one lay 3.03 m off on held-out data (core/verification.py; docs/RESULTS.md,
        sessions 20 and 51). The vouch window is wider than the support window: a vouch
        asks for one closure confirmed on distinct matches, not a run of candidates, and its reach
        is bounded by how far the odometry carries that closure's pose within the tolerance. At 1 %
        drift, 0.5 degrees per 100 m and a closure's own 0.2 m and 0.3-degree error, a right match
        60 m on is predicted within ~1.3 m, inside the 1.5 m tolerance; 100 m on, ~2.2 m. 60 (30
        before) raised the tuning suite's published recall (mean 0.8759 -> 0.8795; simulated town
        0.950 -> 0.992) with no false closure, and with the odometry drifted by 2 % and 1 degree per
        100 m no vouched pose lay 3 m off (docs/RESULTS.md, session 35). Since session 52 the
        window bounds a gap, not a revisit: a closure's reach moves to each match it vouches
        for, each still held to that closure's carried pose, so the drift ends a long revisit's
        vouches. Tuning suite 0.9019 -> 0.9055 (simulated handheld sensor at `default`:
        recall published 0.277 -> 0.537), none false; the `sensors` suite and slam-eval on
        drifted KITTI 00 unchanged (docs/RESULTS.md, session 52).
    odometry_drift, odometry_yaw_drift_deg_per_m: the odometry's error (one standard deviation)
        per metre of travel, in position (a fraction of the distance) and in heading. They set
        no test; they widen the covariance of a weak match published where the vouching
        closures put it: that pose is a closure's, carried along the odometry, so its
        covariance is the closure's own, swung by the closure's heading error over the
        distance carried, plus the odometry's drift over that distance, plus the spread of
        the closures' poses when several vouch and the gap between the match's own pose and
        the carried one, and never narrower than the match's own (core/verification.py). 1 %
        and 0.5 degrees per 100 m: the drift the vouch window was sized for (above); a wheel
        odometry may need several times that. Published closures' covariances against their
        errors: docs/RESULTS.md, session 58.
    rerank_margin, rerank_agreement_m: nearest-place re-ranking. The best-scoring reference
        is often not the nearest one (a reference a few metres off can see more of the same
        scene); after the local stage, the reference nearest the matched pose is aligned too
        and is reported as the match when its alignment scores within rerank_margin (a
        fraction) of the best and implies the same query pose: within rerank_agreement_m,
        turned by at most local_rotation_range_deg (a position alone let an alignment turned
        105 degrees confirm a match on a drifted map; docs/RESULTS.md, session 55): the
        keyframe a back end's own ICP overlaps best. The pose, its covariance, the score
        and the confidence stay the best alignment's (the constraint is re-expressed in the
        nearer reference's frame), so what is published does not depend on it. 0 = off. The
        agreement decides; the margin only refuses an alignment too weak to mean anything.
        0.9 (0.05 before the evidence stayed the best's) was chosen on the whole tuning suite
        (docs/RESULTS.md, "Default changes", sessions 15 and 21); an earlier re-ranking that
        also let a less shifted finalist of another place win, tuned on KITTI 00 alone, lost
        5.5 points on held-out KITTI 02 and was removed.
    map_headings: whether the map's reference headings are known. "known" (default): the
        poses' yaws say how each reference's view is turned. "unknown": they do not (views
        turned by unknown angles, as in BEVPlace's rotated KITTI copies, or references
        tagged with a position alone), and estimate_map_headings could not estimate them
        (or is off): the nearest-place re-ranking then reports the finalist or map
        neighbour of the match the query is nearest to by its own alignment, when the two
        alignments put the references as far apart as the map does (within
        rerank_agreement_m; a neighbour scoring as well as the last finalist), and a place's
        similarity is measured at its views' own angles only. Poses against such a map carry
        the references' unknown turns: the evaluation scores retrieval only there, and the
        localiser node, which publishes poses, refuses it.
    estimate_map_headings: where map_headings is "unknown", each reference's heading is
        estimated from the map itself: the reference is aligned by the local stage on its
        farthest map neighbours within 2 m to three quarters of max_shift_m (at most 4, at
        their prefilter angle and the opposite one), and each alignment, where the two
        positions are known, says which way the neighbour's view is turned (the direction
        between them in the map against the direction in the view) and so the reference's
        (KITTI 00's first 600 frames: 0.74 degrees median error, 1.7 at the 90th
        percentile, 3.0 at most). The map then searches as one whose headings are known: a
        match's pose lies in the map frame, and the nearest-place re-ranking reports the
        reference nearest it (the rotated validation split of the tuning suite: recall@1
        0.995 -> 1.000; docs/RESULTS.md, session 42). Only when every reference has such a
        neighbour; else (a map of one reference per 8 m, say) the headings stay unknown.
        Costs one local stage per reference, once per index, at the first query (~25 ms a
        reference on 2 cores). False: unknown headings stay unknown.
    query_footprint: the cells of the query that count. "window": the map's footprint (the
        disc or square, a field-of-view wedge), its unoccupied cells free space (w).
        "observed": only the cells the query has seen (in each direction, up to its farthest
        return; core.descriptor.observed_cells), the rest weight 0: what lies behind a facade
        or outside a narrow sensor's view is unknown, not free. "auto" (default): observed
        against maps rendered from a global point cloud, whose references are complete
        virtual views that a real scan only partly sees (HKU Avia keyframes, second half on a
        grid rendered from the first: within 1 m 0 % -> 31 %), window against maps of scans,
        where both sides are partial views and free space is evidence (observed costs 1.3
        points on rotated KITTI 00 and 8 of 13 closures on BALM: docs/RESULTS.md).
    global_yaw_window_deg: when > 0 (and the prefilter runs), the global stage scores each
        candidate only at the headings within this many degrees of its prefilter angle or
        the opposite one (the polar spectra's best circular shift refined between angle bins,
        known modulo half a turn; within 2.1 degrees of the match's yaw on every right match
        of sampled KITTI 00 and 00_rot queries, against both one reference per 2 m and per
        8 m). 5 (default) is that error with a margin (2.5) plus half of rotation_step_deg:
        the heading nearest the true yaw is always scored, about 4 of the 72 headings. From
        6 (session 28, unrefined angles, 3.4 degrees of error) to 5 every KITTI revisit of
        the tuning suite but 2 of 4,136 kept its match (same reference, pose within 5 cm),
        and KITTI 00 queries take 13.8 -> 11.7 ms with local_rotation_range_deg 6
        (docs/RESULTS.md, session 30). 0 scores every heading.
    """

    rotation_step_deg: float = 5.0
    top_n: int = 3
    another_place_finalist: bool = True
    max_shift_m: float = 8.0
    local_rotation_range_deg: float = 6.0
    local_rotation_step_deg: float = 2.0
    local_sharpening: float = 0.0
    score_normalisation: str = "cosine"
    min_confidence: float = 0.4
    min_relative_confidence: float = 0.95
    chunk_size: int = 256
    prefilter_top_k: int = 64
    prefilter_rescore_k: int = 0
    prefilter_retry_top_k: int = 256
    prefilter_retry: str = "revisits"
    revisit_check: bool = True
    prefilter_expand_m: float = 6.0
    reference_spectra: str = "auto"
    backend: str = "auto"
    threads: int = 2
    verify_fitness: float = 0.0
    distinct_radius_m: float = 10.0
    min_distinctiveness: float = 0.15
    distinct_aligned_rivals: int = 3
    min_local_distinctiveness: float = 0.3
    consistency_min_support: int = 2
    consistency_window_m: float = 30.0
    consistency_min_separation_m: float = 1.0
    consistency_tolerance_m: float = 1.5
    consistency_tolerance_deg: float = 5.0
    consistency_vouch: bool = True
    consistency_vouch_window_m: float = 60.0
    odometry_drift: float = 0.01
    odometry_yaw_drift_deg_per_m: float = 0.005
    rerank_margin: float = 0.9
    rerank_agreement_m: float = 2.0
    map_headings: str = "known"
    estimate_map_headings: bool = True
    query_footprint: str = "auto"
    global_yaw_window_deg: float = 5.0

    def __post_init__(self) -> None:
        require_parameter(0 < self.rotation_step_deg <= 180
                          and (360 / self.rotation_step_deg).is_integer(),
                 "rotation_step_deg", "a divisor of 360", self.rotation_step_deg)
        require_parameter(self.top_n >= 1, "top_n", ">= 1", self.top_n)
        require_parameter(self.max_shift_m > 0, "max_shift_m", "> 0", self.max_shift_m)
        require_parameter(self.local_rotation_range_deg >= 0, "local_rotation_range_deg", ">= 0",
                 self.local_rotation_range_deg)
        require_parameter(self.local_rotation_step_deg > 0, "local_rotation_step_deg", "> 0",
                 self.local_rotation_step_deg)
        require_parameter(0 <= self.local_sharpening <= 0.25, "local_sharpening",
                          "between 0 and 0.25", self.local_sharpening)
        require_parameter(self.score_normalisation in ("raw", "cosine"), "score_normalisation",
                 "'raw' or 'cosine'", self.score_normalisation)
        require_parameter(0.0 <= self.min_confidence <= 1.0, "min_confidence", "in [0, 1]",
                 self.min_confidence)
        require_parameter(self.min_relative_confidence >= 0.0, "min_relative_confidence",
                          ">= 0 (0 = off)", self.min_relative_confidence)
        require_parameter(self.chunk_size >= 1, "chunk_size", ">= 1", self.chunk_size)
        require_parameter(self.threads >= 1, "threads", ">= 1", self.threads)
        require_parameter(self.prefilter_top_k >= 0, "prefilter_top_k", ">= 0 (0 = exhaustive)",
                 self.prefilter_top_k)
        require_parameter(self.prefilter_rescore_k >= 0, "prefilter_rescore_k",
                          ">= 0 (0 = the prefilter's own ranking)", self.prefilter_rescore_k)
        require_parameter(self.prefilter_retry_top_k >= 0, "prefilter_retry_top_k",
                          ">= 0 (0 = no retry)", self.prefilter_retry_top_k)
        require_parameter(self.prefilter_retry in ("requests", "revisits", "every_query"),
                          "prefilter_retry", "'requests', 'revisits' or 'every_query'",
                          self.prefilter_retry)
        require_parameter(self.prefilter_expand_m >= 0, "prefilter_expand_m", ">= 0",
                 self.prefilter_expand_m)
        require_parameter(self.reference_spectra in ("auto", "memory", "on_demand"),
                          "reference_spectra", "'auto', 'memory' or 'on_demand'",
                          self.reference_spectra)
        require_parameter(self.reference_spectra != "on_demand" or self.prefilter_top_k > 0,
                          "reference_spectra", "'auto' or 'memory' when prefilter_top_k is 0 "
                          "(the exhaustive search reads every reference)",
                          self.reference_spectra)
        require_parameter(self.backend in ("auto", "numpy", "torch"), "backend",
                 "'auto', 'numpy' or 'torch'", self.backend)
        require_parameter(0.0 <= self.verify_fitness <= 1.0, "verify_fitness", "in [0, 1]",
                 self.verify_fitness)
        require_parameter(self.distinct_radius_m > 0, "distinct_radius_m", "> 0",
                          self.distinct_radius_m)
        require_parameter(self.distinct_aligned_rivals >= 0, "distinct_aligned_rivals", ">= 0",
                          self.distinct_aligned_rivals)
        for name in ("min_distinctiveness", "min_local_distinctiveness"):
            require_parameter(0.0 <= getattr(self, name) <= 1.0, name, "in [0, 1]",
                              getattr(self, name))
        require_parameter(self.consistency_min_support >= 0, "consistency_min_support", ">= 0",
                 self.consistency_min_support)
        for name in ("consistency_window_m", "consistency_vouch_window_m",
                     "consistency_tolerance_m", "consistency_tolerance_deg"):
            require_parameter(getattr(self, name) > 0, name, "> 0", getattr(self, name))
        for name in ("odometry_drift", "odometry_yaw_drift_deg_per_m"):
            require_parameter(getattr(self, name) >= 0, name, ">= 0", getattr(self, name))
        require_parameter(0.0 <= self.rerank_margin < 1.0, "rerank_margin", "in [0, 1)",
                 self.rerank_margin)
        require_parameter(self.query_footprint in ("auto", "window", "observed"),
                          "query_footprint", "'auto', 'window' or 'observed'",
                          self.query_footprint)
        require_parameter(self.rerank_agreement_m > 0, "rerank_agreement_m", "> 0",
                 self.rerank_agreement_m)
        require_parameter(self.map_headings in ("known", "unknown"), "map_headings",
                          "'known' or 'unknown'", self.map_headings)
        require_parameter(0.0 <= self.global_yaw_window_deg < 90.0, "global_yaw_window_deg",
                          "in [0, 90)", self.global_yaw_window_deg)
        require_parameter(self.consistency_min_separation_m >= 0, "consistency_min_separation_m",
                          ">= 0",
                 self.consistency_min_separation_m)


_FIELD_ENTRY = re.compile(r"^    ([a-z_]+(?:, [a-z_]+)*): (.*)$")
_FIELD_NAMES_CONTINUED = re.compile(r"^    ([a-z_]+(?:, [a-z_]+)*),$")


def field_descriptions(params_class: type) -> dict[str, str]:
    """Each field's description as its class docstring gives it ("    name[, name]: text",
    continued on deeper-indented lines): one home for the meaning of a parameter, read by the
    nodes' parameter descriptors and docs/PARAMETERS.md."""
    descriptions: dict[str, str] = {}
    names: list[str] = []
    pending: list[str] = []
    for line in (params_class.__doc__ or "").splitlines():
        entry = _FIELD_ENTRY.match(line)
        continued = _FIELD_NAMES_CONTINUED.match(line)
        if continued:
            pending += continued.group(1).split(", ")
            names = []
        elif entry:
            names, pending = pending + entry.group(1).split(", "), []
            for name in names:
                descriptions[name] = entry.group(2)
        elif names and line.startswith("        "):
            for name in names:
                descriptions[name] += " " + line.strip()
        else:
            names = []
    return descriptions


def require_parameter(ok: bool, name: str, expectation: str, value: Any) -> None:
    if not ok:
        raise ConfigError(f"parameter {name} must be {expectation}, got {value!r}")
