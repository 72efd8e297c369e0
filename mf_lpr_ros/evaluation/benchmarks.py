"""The named benchmark suites: dataset pairs under a root, their protocols and presets, and
the figures published for them (evaluation.suite runs them)."""

from __future__ import annotations

from dataclasses import replace

from mf_lpr_ros.evaluation.protocol import Protocol
from mf_lpr_ros.evaluation.suite import Published, Rule, Suite
from mf_lpr_ros.sim.simulator import SENSOR_WORLDS

# BEVPlace's KITTI protocol (its own BEV images): database and query frame ranges per sequence,
# every database frame a reference, a query counts when a database frame lies within 5 m.
_BEVPLACE_FRAMES = {"00": ((0, 2999), (3200, 4540)), "02": ((0, 3399), (3600, 4660)),
                    "05": ((0, 999), (1200, 2750)), "06": ((0, 599), (800, 1100))}


# BEVPlace's reported recall@1 (%), normal and rotated copies.
_BEVPLACE_RECALL = {"00": (99.7, 99.6), "02": (98.1, 93.5), "05": (99.3, 98.9),
                    "06": (100.0, 100.0)}


def _bevplace(folder: str, sequences: tuple[str, ...]) -> tuple[tuple[Rule, ...], tuple]:
    """Rules (each sequence and its _rot copy under folder) and BEVPlace's published recall."""
    rules, published = [], []
    for sequence in sequences:
        database, queries = _BEVPLACE_FRAMES[sequence]
        for suffix, recall in zip(("", "_rot"), _BEVPLACE_RECALL[sequence]):
            pattern = f"{folder}/{sequence}{suffix}"
            protocol = Protocol(5.0, reference_spacing_m=0.0, reference_frames=database,
                                query_frames=queries, headings_known=suffix != "_rot")
            rules.append(Rule("single", "kitti", protocol, (pattern,)))
            published.append(Published(pattern.replace("/", "_"), "BEVPlace (published)",
                                       recall / 100.0))
    return tuple(rules), tuple(published)


_BEVPLACE_TUNING = _bevplace("kitti_bev", ("00",))


# The same queries against a database thinned to one reference per 8 m: the queries then lie
# 2-4 m from their nearest reference, where BEVPlace's own protocol (every frame a reference)
# saturates the tuning sequence. The candidate stage loses there as on held-out KITTI 02
# (docs/RESULTS.md, session 16).
_BEVPLACE_SPARSE_DATABASE = tuple(
    Rule("single", "kitti", Protocol(5.0, reference_spacing_m=8.0,
                                     reference_frames=_BEVPLACE_FRAMES["00"][0],
                                     query_frames=_BEVPLACE_FRAMES["00"][1],
                                     headings_known=suffix != "_rot"),
         (f"kitti_bev/00{suffix}",), label="8 m database") for suffix in ("", "_rot"))


# KITTI 00 on BEVPlace's protocol, its queries described as if half of the world's 2 m columns
# had gone since the database was recorded (Protocol.query_thinning), the database whole.
# Retrieval barely moves there and right matches fail the confidence test, as 46 of the 107
# right matches that held-out KITTI 02 left unpublished on that protocol did: they stay
# unpublished unless a confirmed closure vouches for them (docs/RESULTS.md, sessions 50 and
# 51).
_BEVPLACE_THINNED_QUERIES = (
    Rule("single", "kitti", replace(_BEVPLACE_TUNING[0][0].protocol, query_thinning=0.5),
         ("kitti_bev/00",), label="thinned queries"),)


# The tuning suite's validation split: KITTI 00 BEV cut where BEVPlace does not cut it (the
# first 1500 frames as the database, frames 1700 on as queries), a split nothing was tuned on;
# since session 41 on the rotated copy too: besides BEVPlace's own, the only rotated pair
# whose database is every frame.
_KITTI00_VALIDATION = Protocol(5.0, reference_spacing_m=0.0, reference_frames=(0, 1499),
                               query_frames=(1700, 4540))


# The simulated worlds of the tuning suite: the only tuning sets where `auto` meets a dense
# spinning sensor next to a sparse one (docs/RESULTS.md, session 15), and, since session 27, a
# sparse sensor carried by hand, which tilts (the only tuning set where a sensor that needs
# submaps revisits mapped places with its roll and pitch changing); since session 37, a dense
# 360-degree sensor carried by hand, also under the `handheld` preset (the preset for such a
# sensor, which published false closures on it: docs/RESULTS.md, session 37).
_SIMULATED_WORLDS = ("urban", "forest", "sparse", "handheld", "dense_handheld")

# The sparse sensors' worlds under the `livox` preset too (since session 27).
_LIVOX_WORLDS = ("sparse", "handheld")


# The presets a user picks for a sensor of that kind, on the suite "sensors".
_SENSOR_PRESETS = ("auto", "default", "livox", "handheld")


_BEVPLACE_HOLDOUT = _bevplace("holdout/kitti_bev", ("02", "05", "06"))

# The same pairs searched as relocalisation requests: BEVPlace's protocol asks where each scan
# is, which is what `mf-lpr localise` and the `~/relocalise` service answer, with the
# prefilter's wider retry for a weak match (since session 41, beside the stream's figures).
_BEVPLACE_REQUESTS = tuple(
    replace(rule, protocol=replace(rule.protocol, requests=True), label="requests")
    for rule in _BEVPLACE_TUNING[0] + _BEVPLACE_HOLDOUT[0])


_BEVPLACE_TEXT = ("BEVPlace's KITTI protocol on its BEV images: database frames 00: 0-2999, "
                  "02: 0-3399, 05: 0-999, 06: 0-599 (every frame a reference), queries 00: "
                  "3200-4540, 02: 3600-4660, 05: 1200-2750, 06: 800-1100, 5 m (2-D); each "
                  "sequence and its _rot copy (every frame turned by its own random yaw, poses "
                  "unrotated: searched as a map whose headings are unknown, each estimated "
                  "from its neighbours' alignments; only retrieval is scored there, the pose "
                  "figures are NaN), "
                  "with BEVPlace's published recall@1 beside; each searched as a loop-closure "
                  "stream searches, and as relocalisation requests ([requests]: a weak match "
                  "searched again over the prefilter's wider list)")


_PAPER_NCLT = Protocol(25.0, reference_spacing_m=4.0, query_spacing_m=10.0)


_PAPER_OXFORD = Protocol(25.0, reference_spacing_m=4.0, query_spacing_m=10.0)


_WILDPLACES_INTER = Protocol(3.0, reference_spacing_m=2.0)


_WILDPLACES_INTRA = Protocol(3.0, reference_spacing_m=2.0, exclude_recent_s=600.0)


SUITES: dict[str, Suite] = {suite.name: suite for suite in (
    Suite("nclt-paper",
          "NCLT, the paper's pairs: references 2013-02-23 and 2013-04-05 against every 2012 "
          "session under --root (the paper used nine); refs >= 4 m apart, a query per 10 m, "
          "25 m tolerance",
          (Rule("cross", "nclt", _PAPER_NCLT, ("2013-02-23", "2013-04-05"), ("2012-*",)),)),
    Suite("nclt-ring",
          "NCLT as RING, RING++ and DeepRING evaluate it, as we read those papers (check before "
          "citing): database 2012-02-04, queries 2012-03-17; refs every 2 m, a query per 10 m, "
          "5 m tolerance",
          (Rule("cross", "nclt", Protocol(5.0, reference_spacing_m=2.0, query_spacing_m=10.0),
                ("2012-02-04",), ("2012-03-17",)),)),
    Suite("oxford-paper",
          "Oxford Radar RobotCar, the paper's pairs: references 2019-01-11-12-26-55 and "
          "2019-01-10-11-46-21 against the 2019-01-14 to 2019-01-18 sessions (left Velodyne); "
          "refs >= 4 m apart, a query per 10 m, 25 m tolerance",
          (Rule("cross", "oxford", _PAPER_OXFORD,
                ("2019-01-11-12-26-55", "2019-01-10-11-46-21"),
                ("2019-01-14-*", "2019-01-15-*", "2019-01-16-*", "2019-01-17-*",
                 "2019-01-18-*")),)),
    Suite("wildplaces-paper",
          "Wild-Places inter-sequence (the paper's Wild-Places table): every ordered pair of the "
          "four sequences in each forest, queries from the release's evaluation split "
          "(<Forest>_evaluation_query.pickle under --root), refs every 2 m, 3 m tolerance",
          (Rule("ordered", "wildplaces", _WILDPLACES_INTER, ("Venman/V-0[1-4]",),
                query_split="{group}_evaluation_query.pickle"),
           Rule("ordered", "wildplaces", _WILDPLACES_INTER, ("Karawatha/K-0[1-4]",),
                query_split="{group}_evaluation_query.pickle"))),
    Suite("wildplaces-intra",
          "Wild-Places intra-sequence: loop closures within V-03, V-04, K-03 and K-04, "
          "references at least 600 s older, refs every 2 m, 3 m tolerance",
          (Rule("single", "wildplaces", _WILDPLACES_INTRA,
                ("Venman/V-03", "Venman/V-04", "Karawatha/K-03", "Karawatha/K-04")),)),
    Suite("kitti-bevplace",
          _BEVPLACE_TEXT + "; 00 (tuning) and the held-out 02, 05, 06 (--root ../shared/data)",
          _BEVPLACE_TUNING[0] + _BEVPLACE_HOLDOUT[0] + _BEVPLACE_REQUESTS,
          _BEVPLACE_TUNING[1] + _BEVPLACE_HOLDOUT[1]),
    Suite("kitti-bevplace-00", _BEVPLACE_TEXT + "; 00 and 00_rot only (the tuning sequence)",
          _BEVPLACE_TUNING[0] + _BEVPLACE_REQUESTS[:2], _BEVPLACE_TUNING[1]),
    Suite("real-holdout",
          "The real held-out sets of ../shared/data/holdout (measure once, never tune): the Livox "
          "Mid-360 campus loop's own loop closures (references >= 40 s older, 5 m) and the Livox "
          "Avia site's session2 against a session1 map (3 m), each with preset auto and with the "
          "named preset chosen for the sensor beforehand (default for the Mid-360, handheld for "
          "the handheld Avia) and with livox (submaps) for both",
          (Rule("single", "auto", Protocol(5.0, exclude_recent_s=40.0),
                ("holdout/campus_mid360_loop",), by_preset=True),
           Rule("single", "default", Protocol(5.0, exclude_recent_s=40.0),
                ("holdout/campus_mid360_loop",), by_preset=True),
           Rule("cross", "auto", Protocol(3.0), ("holdout/hku_avia_2sessions/session1",),
                ("holdout/hku_avia_2sessions/session2",), by_preset=True),
           Rule("cross", "handheld", Protocol(3.0), ("holdout/hku_avia_2sessions/session1",),
                ("holdout/hku_avia_2sessions/session2",), by_preset=True),
           Rule("single", "livox", Protocol(5.0, exclude_recent_s=40.0),
                ("holdout/campus_mid360_loop",), by_preset=True),
           Rule("cross", "livox", Protocol(3.0), ("holdout/hku_avia_2sessions/session1",),
                ("holdout/hku_avia_2sessions/session2",), by_preset=True))),
    Suite("real-tuning",
          "The real tuning sets with preset auto beside the named preset: BALM handheld "
          "(3 m, 50 frames apart) and the HKU Avia keyframes (5 m, 50 frames apart)",
          (Rule("single", "auto", Protocol(3.0, exclude_recent_frames=50), ("balm_realworld",),
                by_preset=True),
           Rule("single", "handheld", Protocol(3.0, exclude_recent_frames=50),
                ("balm_realworld",), by_preset=True),
           Rule("single", "auto", Protocol(5.0, exclude_recent_frames=50), ("hku_mb_livox",),
                by_preset=True),
           Rule("single", "default", Protocol(5.0, exclude_recent_frames=50), ("hku_mb_livox",),
                by_preset=True))),
    Suite("tuning",
          "Every tuning set in one table, for choosing defaults (a default changes only when "
          "the mean rises and no set drops more than a point; docs/RESULTS.md keeps each "
          "change's table): KITTI 00 and 00_rot on BEVPlace's protocol, KITTI 00 every-frame "
          "loop closures (kitti, 5 m, 100 frames apart), BALM (handheld and auto, 3 m, 50 "
          "frames), the HKU Avia keyframes (default, auto and livox, 5 m, 50 frames), the "
          "simulator's urban (VLP-16), forest (HDL-32), sparse (Mid-360-like), handheld "
          "(the sparse sensor swaying in the hand) and dense handheld (a 64-beam sensor swaying "
          "in the hand) worlds, day 2 off the worlds' grid against day 1 (auto and default, "
          "livox for the sparse two, handheld for the dense handheld one, 5 m) and, as "
          "validation, KITTI 00 and 00_rot cut elsewhere (database frames 0-1499, queries "
          "1700-4540) and, harder, 00 and 00_rot on BEVPlace's frames with one reference per "
          "8 m, and 00 on BEVPlace's protocol with half of the world's 2 m columns gone from "
          "every query",
          _BEVPLACE_TUNING[0] + (
              Rule("single", "kitti", Protocol(5.0, exclude_recent_frames=100),
                   ("kitti_bev/00",), label="closures"),
              Rule("single", "handheld", Protocol(3.0, exclude_recent_frames=50),
                   ("balm_realworld",), by_preset=True),
              Rule("single", "auto", Protocol(3.0, exclude_recent_frames=50),
                   ("balm_realworld",), by_preset=True),
              Rule("single", "default", Protocol(5.0, exclude_recent_frames=50),
                   ("hku_mb_livox",), by_preset=True),
              Rule("single", "auto", Protocol(5.0, exclude_recent_frames=50),
                   ("hku_mb_livox",), by_preset=True),
              Rule("single", "livox", Protocol(5.0, exclude_recent_frames=50),
                   ("hku_mb_livox",), by_preset=True),
              Rule("simulated", "auto", Protocol(5.0), _SIMULATED_WORLDS, by_preset=True),
              Rule("simulated", "default", Protocol(5.0), _SIMULATED_WORLDS, by_preset=True),
              Rule("simulated", "livox", Protocol(5.0), _LIVOX_WORLDS, by_preset=True),
              Rule("simulated", "handheld", Protocol(5.0), ("dense_handheld",),
                   by_preset=True),
              Rule("single", "kitti", _KITTI00_VALIDATION, ("kitti_bev/00",),
                   label="validation"),
              Rule("single", "kitti", replace(_KITTI00_VALIDATION, headings_known=False),
                   ("kitti_bev/00_rot",), label="validation")) + _BEVPLACE_SPARSE_DATABASE
          + _BEVPLACE_THINNED_QUERIES,
          _BEVPLACE_TUNING[1]),
    Suite("sensors",
          f"The presets {', '.join(_SENSOR_PRESETS)} on simulated sensors and mounts the "
          f"tuning suite does not hold (sim.simulator.SENSOR_WORLDS: "
          f"{', '.join(SENSOR_WORLDS)}), day 2 off the grid against day 1, 5 m: a "
          "check after a default changes (no preset may publish a false closure; auto should "
          "do what default does or better), not a set to choose defaults on",
          tuple(Rule("simulated", name, Protocol(5.0), tuple(SENSOR_WORLDS), by_preset=True)
                for name in _SENSOR_PRESETS)),
    Suite("shared-data",
          "The development sets of ../shared/data (the project's acceptance table): BALM "
          "handheld, HKU main building (Livox) and KITTI 00 BEV, single-sequence loop closures",
          (Rule("single", "handheld", Protocol(3.0, exclude_recent_frames=50),
                ("balm_realworld",)),
           Rule("single", "default", Protocol(5.0, exclude_recent_frames=50),
                ("hku_mb_livox",)),
           Rule("single", "kitti", Protocol(5.0, exclude_recent_frames=100, query_every=20),
                ("kitti_bev/00",)))),
)}
