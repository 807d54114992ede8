"""Issue 14 item 1: the chain uses the later cycles too. A step learned from the recent cycle pairs when no
web depth is configured, a cycle measured from the chain's earlier cycles when its anchor cannot reach it,
and untrusted rows re-issued (revision 1) once a later cycle resolves them (chain.RigChain, method.md 6.2)."""

from __future__ import annotations

import dataclasses
import logging
from types import SimpleNamespace

import numpy as np
from test_association_honesty import HEIGHTS, PRIOR, noisy_cycles, plate

from uwbcl import chain, outputs
from uwbcl.acquisition import live
from uwbcl.records import AssociationSettings, CycleResult, Displacement, ProcessingSettings

BLIND = AssociationSettings()  # no web-depth prior


def ok_rows(rows, rigs):
    """(number of rows, ok rows' largest |error| in retreat/creep, fraction within 3 x bound, revisions)."""
    errors, covered, revised = [], [], 0
    for r in rows:
        if r.displacement.status != "ok":
            continue
        e = np.abs(r.displacement.advance_m[:2] - (rigs[r.cycle.cycle] - rigs[r.reference.cycle])[:2])
        errors.append(e.max())
        covered.append(bool(np.all(e <= 3 * r.displacement.bound_m[:2])))
        revised += r.revision
    return len(errors), max(errors), float(np.mean(covered)), revised


def fed(cycles, settings=BLIND):
    """A RigChain fed the cycles one at a time, each row's first-issued status, and the cycles re-issued."""
    rc = chain.RigChain(settings)
    first_issue, reissued = {}, []
    for c in cycles:
        row = rc.add(c)
        if row is not None:
            first_issue.setdefault(row.cycle.cycle, row.displacement.status)
        reissued += [r.cycle.cycle for r in rc.revised]
    return rc, first_issue, reissued


def test_without_a_web_depth_the_step_learned_from_the_cycles_makes_more_rows_ok_and_none_wrong():
    # 8 rigs x 15 rows, no prior: 86 ok rows without the second look, 102 with it (measured 2026-11-24),
    # largest ok error 11 mm, every ok row within 3 x its bound.
    counts = {}
    for second_look in (False, True):
        total, worst, cover = 0, 0.0, []
        for seed in range(8):
            cycles, rigs = noisy_cycles(16, seed=200 + seed)
            settings = dataclasses.replace(BLIND, second_look=second_look)
            n, w, c, _ = ok_rows(chain.rig_series(cycles, settings), rigs)
            total, worst = total + n, max(worst, w)
            cover.append(c)
        counts[second_look] = total
        assert worst < 0.02 and min(cover) == 1.0
    assert counts[True] >= counts[False] + 10


def test_a_step_is_learned_only_when_the_pairs_agree_on_it_by_the_margin():
    cycles, rigs = noisy_cycles(6, seed=5)
    rc = chain.RigChain(dataclasses.replace(BLIND, motion_model=False))
    assert rc.add(cycles[0]) is None
    rc.add(cycles[1])
    assert rc.learned_step() is None  # one pair: nothing to compare it with
    for c in cycles[2:]:
        rc.add(c)
    step, sigma = rc.learned_step()
    np.testing.assert_allclose(step[0], 0.9, atol=0.1)
    np.testing.assert_array_equal(sigma, chain.MOTION_SIGMA_FLOOR_M)
    empty = chain.RigChain(BLIND)
    for c in cycles[:4]:
        empty.add(CycleResult(c.rig_id, c.cycle, c.start_time, HEIGHTS, c.plates[:1]))
    assert empty.learned_step() is None  # single plates: every step fits every pair equally


def test_steps_that_differ_by_the_webs_variation_are_one_learned_step_not_rivals():
    """Webs of 0.90, 0.80 and 0.87 m: each pair proposes its own step, centimetres apart; they are the same
    hypothesis (within 3 sigma of M4's per-cycle sigma), so they support it together instead of standing as
    one another's rivals (which left a short blind run without a learned step, and its rows ambiguous)."""
    webs = [0.0, 0.90, 0.80, 0.87, 0.90, 0.85]
    cycles, rigs = noisy_cycles(6, seed=5, webs_m=webs)
    rc = chain.RigChain(dataclasses.replace(BLIND, motion_model=False))
    for c in cycles[:4]:
        rc.add(c)
    steps = [t for a, b in zip(cycles[:4], cycles[1:4]) for t, _ in rc._scores(a, b)]
    assert max(abs(t[0] - 0.80) for t in steps) > chain.MOTION_SIGMA_FLOOR_M[0]  # candidates 5-10 cm apart
    step, _ = rc.learned_step()
    assert 0.78 <= step[0] <= 0.92


def test_a_chain_started_again_after_an_ambiguous_first_row_joins_it_once_later_cycles_give_the_step(
        caplog):
    """No prior, two plates in common: the first row is ambiguous, the chain starts again at cycle 1; once the
    later pairs (not 0 -> 1) give a step, 0 -> 1 is measured with it, re-issued, and the later rows join
    chain 0 with cumulative values from cycle 0 (re-issued too). The log's warnings end as the rows do."""
    cycles, rigs = noisy_cycles(6, seed=5, window=(0.0, 3.0))
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        rc, first_issue, reissued = fed(cycles)
    assert "the restart above undone" in caplog.records[-1].getMessage()
    assert first_issue[1] == "ambiguous" and 1 in reissued
    assert [r.displacement.status for r in rc.rows] == ["ok"] * 5
    assert [r.chain for r in rc.rows] == [0] * 5 and rc.rows[0].revision == 1
    for r in rc.rows:
        error = np.abs(r.cumulative_m[:2] - (rigs[r.cycle.cycle] - rigs[0])[:2])
        assert np.all(error <= 3.0 * r.cumulative_bound_m[:2]), (r.cycle.cycle, error)


def test_untrusted_rows_the_later_step_links_to_the_old_chain_are_reissued_even_when_the_restart_is_not():
    """No prior: rows 1 and 2 are ambiguous and the chain starts again at cycle 3. The later cycles' step
    links 0 -> 1 -> 2 but not 2 -> 3: rows 1 and 2 are re-issued in chain 0 with cumulative values from cycle
    0; chain 1 stays as it was (seed 163, a 3 m view; seed 4 until backward translations were no
    hypothesis, eq. M2b, 2026-11-28)."""
    cycles, rigs = noisy_cycles(8, seed=163, window=(0.0, 3.0), sigma=0.004)
    rc, first_issue, reissued = fed(cycles)
    assert first_issue[1] != "ok" and first_issue[2] != "ok" and {1, 2} <= set(reissued)
    by_cycle = {r.cycle.cycle: r for r in rc.rows}
    for c in (1, 2):
        r = by_cycle[c]
        assert (r.displacement.status, r.chain, r.revision, r.reference.cycle) == ("ok", 0, 1, c - 1)
        error = np.abs(r.cumulative_m[:2] - (rigs[c] - rigs[0])[:2])
        assert np.all(error <= 3.0 * r.cumulative_bound_m[:2]), (c, error)
    assert by_cycle[3].chain == 1 and by_cycle[3].displacement.status != "ok"
    assert all(by_cycle[c].chain == 1 for c in range(4, 8))


def test_a_rejoin_never_rests_on_a_step_that_only_ambiguous_pairs_agree_on():
    """A 2 m view with two or three plates a cycle, no prior: every row is ambiguous and nothing is learned,
    but with the pair 3 -> 4 left out the other pairs agree on a wrong step. The rejoin may use a learned
    step only when the step learned from all the pairs, or an ok row of the new chain, agrees with it; here
    neither exists, so no row is re-issued ok (without that rule, 3 -> 4 was re-issued ok 1,066 mm off;
    measured 2026-11-24)."""
    cycles, rigs = noisy_cycles(10, seed=65, window=(0.0, 2.0), sigma=0.004)
    rows = chain.rig_series(cycles, BLIND)
    for r in rows:
        if r.displacement.status == "ok":
            e = np.abs(r.displacement.advance_m[:2] - (rigs[r.cycle.cycle] - rigs[r.reference.cycle])[:2])
            assert e.max() < 0.05, (r.cycle.cycle, r.reference.cycle, e)


def test_an_untrusted_row_after_the_anchor_is_reissued_once_the_next_cycles_give_the_step():
    """No prior, a 2 m view: cycle 7 is ambiguous from the anchor 6, and cycle 8 is ambiguous too. Once the
    step learned without the pair 6 -> 7 (and confirmed by the chain's ok rows) exists, 6 -> 7 is measured
    again with it as cycle 8 arrives, re-issued ok (revision 1), and the anchor moves to 7; no later cycle
    had to bridge it (seed 65; seed 300 until backward translations were no hypothesis, eq. M2b)."""
    cycles, rigs = noisy_cycles(10, seed=65, window=(0.0, 2.0), sigma=0.004)
    rc = chain.RigChain(BLIND)
    for c in cycles[:8]:
        rc.add(c)
    assert [r.cycle.cycle for r in rc.revised] == [] and rc.rows[-1].displacement.status == "ambiguous"
    first_seven = rc.rows[-1]
    row = rc.add(cycles[8])
    assert row.displacement.status != "ok"
    assert [(r.cycle.cycle, r.reference.cycle, r.displacement.status, r.revision) for r in rc.revised] == \
        [(7, 6, "ok", 1)]
    seven = rc.revised[0]
    assert first_seven.cycle.cycle == 7 and first_seven.displacement.status == "ambiguous"
    e = np.abs(seven.displacement.advance_m[:2] - (rigs[7] - rigs[6])[:2])
    assert np.all(e <= 3.0 * seven.displacement.bound_m[:2]), e
    previous = next(r for r in rc.rows if r.cycle.cycle == 6)
    expected = previous.cumulative_m + seven.displacement.advance_m
    np.testing.assert_allclose(seven.cumulative_m, expected, atol=1e-12)


def _attempt(status: str, retreat_m: float) -> Displacement:
    return Displacement(np.array([retreat_m, 0.0, 0.0]), np.zeros(3), 1, 0.0, status, [(0, 0)],
                        bound_m=np.full(3, 0.02), margin=9.0)


def test_a_withheld_row_shows_the_more_informative_of_its_attempts_from_the_anchor_and_the_cycle_before(
        monkeypatch):
    """Cycle 2 is withheld from the anchor 1; cycle 3 across the gap from 1 is a translation outside the prior
    (prior_conflict, 0.15 m: a wrong match), from 2 a unique match whose bound is too wide (low_confidence,
    0.93 m). The row shows the attempt from 2; an inconsistent attempt (from the anchor: the bridge in
    reserve; from 2: not one) and ties keep the anchor's (docs/outputs.md section 3; seen on draw 1900's
    r1914)."""
    cycles, _ = noisy_cycles(4, seed=0)

    def run(attempts):
        monkeypatch.setattr(chain.RigChain, "_measure", lambda self, a, b, prior=None: attempts.get(
            (a.cycle, b.cycle), _attempt("ambiguous", 0.9 * (b.cycle - a.cycle))))
        rows = chain.rig_series(cycles, dataclasses.replace(PRIOR, second_look=False))
        return {r.cycle.cycle: (r.reference.cycle, r.displacement.status, r.displacement.retreat_m)
                for r in rows}

    ok = {(0, 1): _attempt("ok", 0.9), (1, 2): _attempt("low_confidence", 0.9)}
    rows = run({**ok, (1, 3): _attempt("prior_conflict", 0.15), (2, 3): _attempt("low_confidence", 0.93)})
    assert rows[3] == (2, "low_confidence", 0.93) and rows[2] == (1, "low_confidence", 0.9)
    rows = run({**ok, (1, 3): _attempt("inconsistent", 1.8), (2, 3): _attempt("low_confidence", 0.93)})
    assert rows[3] == (1, "inconsistent", 1.8)
    rows = run({**ok, (1, 3): _attempt("ambiguous", 1.8), (2, 3): _attempt("ambiguous", 0.93)})
    assert rows[3] == (1, "ambiguous", 1.8)
    rows = run({**ok, (1, 3): _attempt("low_confidence", 1.8), (2, 3): _attempt("prior_conflict", 0.93)})
    assert rows[3] == (1, "low_confidence", 1.8)
    # an inconsistent row is the bridge held in reserve: one from the cycle before is not shown as one
    rows = run({**ok, (1, 3): _attempt("too_few_targets", np.nan), (2, 3): _attempt("inconsistent", 0.93)})
    assert rows[3][:2] == (1, "too_few_targets")


def test_a_cycle_whose_anchor_saw_one_plate_is_measured_from_the_chains_earlier_cycle():
    cycles, rigs = noisy_cycles(10, seed=0)
    cycles[4] = CycleResult("rig-1", 4, cycles[4].start_time, HEIGHTS, cycles[4].plates[:1])
    rows = {r.cycle.cycle: r for r in chain.rig_series(cycles, PRIOR)}
    assert rows[4].displacement.status == "ok"  # the one plate, with the prior
    r5 = rows[5]  # its plate has left the view by cycle 5: measured from cycle 3
    assert (r5.reference.cycle, r5.displacement.status, r5.chain) == (3, "ok", 0)
    assert np.max(np.abs(r5.cumulative_m[:2] - (rigs[5] - rigs[0])[:2])) < 0.01
    off = {r.cycle.cycle: r for r in chain.rig_series(cycles, dataclasses.replace(PRIOR, second_look=False))}
    assert off[5].displacement.status != "ok" and off[9].chain > 0  # without it the chain breaks


def test_an_untrusted_row_is_reissued_as_revision_1_when_a_later_cycle_resolves_it():
    cycles, rigs = noisy_cycles(10, seed=1)
    rc = chain.RigChain(BLIND)
    first_issue, reissued = {}, []
    for c in cycles:
        row = rc.add(c)
        if row is not None:
            first_issue[c.cycle] = (row.displacement.status, row.revision)
        reissued += [(r.cycle.cycle, c.cycle) for r in rc.revised]
    assert reissued, "no row was resolved by a later cycle"
    for cycle, by in reissued:
        assert by > cycle and first_issue[cycle] != ("ok", 0)  # issued untrusted, re-issued later
        row = next(r for r in rc.rows if r.cycle.cycle == cycle)
        assert (row.displacement.status, row.revision) == ("ok", 1)
        assert np.all(np.isfinite(row.cumulative_m)) and np.all(np.isfinite(row.cumulative_bound_m))
        err = np.abs(row.cumulative_m[:2] - (rigs[cycle] - rigs[0])[:2])
        assert np.all(err <= 3 * row.cumulative_bound_m[:2] + 1e-4)
    records = outputs.displacement_records(rc.rows)
    assert {rec["cycle"] for rec in records if rec["revision"] == 1} == {c for c, _ in reissued}


def test_the_live_processor_appends_the_reissued_rows_after_the_cycle_that_resolved_them(monkeypatch):
    cycles, _ = noisy_cycles(10, seed=1)
    by_cycle = {c.cycle: c for c in cycles}
    monkeypatch.setattr(live.pipeline, "locate_cycle", lambda passes, settings: by_cycle[passes[0].cycle])
    monkeypatch.setattr(live.geo, "doppler_wrong_side", lambda scan: None)  # the stand-ins have no echo
    # the passes are stand-ins without echoes: plates only (the rib registration needs the lowest pass's echo)
    plates_only = dataclasses.replace(BLIND, rib_registration=False)
    proc = live.LiveProcessor(ProcessingSettings(association=plates_only))
    try:
        results = []
        for c in cycles:
            passes = [SimpleNamespace(cycle=c.cycle, geometry=SimpleNamespace(height_m=h),
                                      range_window_start_s=2e-8) for h in HEIGHTS]  # (metres out: no crop)
            results += proc._process(c.cycle, passes, True, c.start_time)
    finally:
        proc.close()
    reissues = [r for r in results if r["revision"] == 1]
    assert reissues and all(r["status"] == "ok" for r in reissues)
    for r in reissues:  # after the row of the cycle that resolved it, never instead of the first issue
        first = next(i for i, x in enumerate(results) if x["cycle"] == r["cycle"])
        assert results.index(r) > first and results[first]["revision"] == 0
    assert "revision" in live.RESULT_COLUMNS and "revision" in outputs.DISPLACEMENT_COLUMNS


def test_a_row_resolved_with_the_next_cycles_plates_names_only_its_own_plates():
    """`_resolve_through` matches a against b's plates plus c's moved into b's frame; the re-issued row is
    b's, so its pairs name b's plates only (a moved plate's index beyond b's once broke targets.csv)."""

    rib = np.array([[1.0, -2.5, 0.6], [2.1, -2.5, 1.3], [3.4, -2.5, 0.6]])
    step = np.array([0.9, 0.002, 0.0])
    a = CycleResult("r", 0, "2026-11-24T00:00:00Z", HEIGHTS, [plate(p) for p in rib])
    b = CycleResult("r", 1, "2026-11-24T01:00:00Z", HEIGHTS, [plate(rib[1] - step)])
    c = CycleResult("r", 2, "2026-11-24T02:00:00Z", HEIGHTS, [plate(p - 2 * step) for p in rib])
    rc = chain.RigChain(PRIOR)
    for cycle in (a, b, c):
        rc.add(cycle)
    d_ab = rc._resolve_through(a, b, c, rc._measure(b, c))
    assert d_ab is not None and d_ab.n_targets == 3  # the moved plates were matched too
    assert d_ab.pairs and all(j < len(b.plates) for _, j in d_ab.pairs)
    np.testing.assert_allclose(d_ab.advance_m[:2], step[:2], atol=1e-3)


def test_every_trusted_cumulative_is_its_references_plus_its_own_advance_through_restarts_and_joins():
    """Through restarts, re-issues and joins (with and without a prior, sparse and dense views), an ok row's
    cumulative value is the cumulative of the cycle it was measured from plus its own advance, in one
    chain."""
    checked = joined = 0
    for seed in range(20):
        for settings in (BLIND, PRIOR):
            for window in ((0.0, 2.0), (0.0, 3.0)):
                cycles, _ = noisy_cycles(10, seed=seed, window=window, sigma=0.004)
                rows = chain.rig_series(cycles, settings)
                by_cycle = {r.cycle.cycle: r for r in rows}
                for r in rows:
                    if r.displacement.status != "ok" or not np.all(np.isfinite(r.cumulative_m)):
                        continue
                    ref = by_cycle.get(r.reference.cycle)
                    if ref is None:  # measured from the rig's first cycle, the origin
                        assert r.chain == 0 and r.reference.cycle == cycles[0].cycle
                        base = np.zeros(3)
                    else:
                        assert ref.chain == r.chain and np.all(np.isfinite(ref.cumulative_m))
                        base = ref.cumulative_m
                    np.testing.assert_allclose(r.cumulative_m, base + r.displacement.advance_m, atol=1e-12)
                    checked += 1
                joined += any(r.revision and r.chain == 0 for r in rows)
    assert checked > 500 and joined > 10


def _issued(row):
    d = row.displacement
    values = np.concatenate([d.advance_m, d.bound_m, row.cumulative_m, row.cumulative_bound_m])
    return row.cycle.cycle, row.reference.cycle, d.status, values.tobytes(), row.chain, row.revision


def test_a_live_chain_that_forgets_what_no_later_cycle_consults_stays_small_and_issues_the_same_rows():
    """`uwbcl acquire --process` runs for months: its chain keeps only what later cycles can consult
    (`RigChain.forget` after every cycle), and every row it issues or re-issues is the whole chain's."""
    compared = restarts = reserved = 0
    for seed, sigma in ((300, 0.004), (301, 0.004), (302, 0.004), (303, 0.008), (304, 0.008), (305, 0.008)):
        for settings in (BLIND, PRIOR):
            cycles, _ = noisy_cycles(45, seed=seed, window=(0.0, 2.0), sigma=sigma)
            whole, live_chain = chain.RigChain(settings), chain.RigChain(settings)
            longest = 0
            for c in cycles:
                rows = [whole.add(c), *whole.revised]
                kept = [live_chain.add(c), *live_chain.revised]
                live_chain.forget()
                assert [None if r is None else _issued(r) for r in kept] == \
                    [None if r is None else _issued(r) for r in rows]
                compared += len(rows)
                # what the rows depend on: the rejoin's witnesses and the reserve row
                for r in whole.rows:
                    if r.displacement.status == "ok" and r.chain == whole._chain:
                        probe = (chain._step_per_cycle(r), np.full(3, 1e-9))  # its own witness only
                        assert (live_chain._confirmed(probe) is None) == (whole._confirmed(probe) is None)
                if whole._reserve is not None:
                    reserved += 1
                    assert live_chain.rows[live_chain._reserve[0]] is not None and \
                        live_chain.rows[live_chain._reserve[0]].cycle is whole.rows[whole._reserve[0]].cycle
                longest = max(longest, len(live_chain.rows), len(live_chain._covs))
            restarts += max(r.chain for r in whole.rows)
            bound = 2 * (chain.LEARN_PAIRS + chain.DEFAULT_MAX_BRIDGE_CYCLES)
            assert len(whole.rows) == 44 and longest <= bound
    assert compared > 500 and restarts > 0 and reserved > 0  # restarts, joins and a reserve exercised


def test_a_chain_that_starts_on_a_cycle_with_no_plates_counts_from_the_next_cycle_with_one_origin():
    """One origin per chain (docs/outputs.md section 3): a restart that lands on an empty cycle, and an empty
    first cycle, move the origin to the next cycle; the empty cycle's row is nan, not a second 0."""
    cycles, rigs = noisy_cycles(12, seed=3)
    empty = {0, 4, 5, 6}  # the rig's first cycle, and three in a row: max_bridge_cycles restarts on cycle 6
    cycles = [dataclasses.replace(c, plates=[]) if c.cycle in empty else c for c in cycles]
    rows = chain.rig_series(cycles, PRIOR)
    by_cycle = {r.cycle.cycle: r for r in rows}
    origins = {}
    for r in rows:
        if np.all(r.cumulative_m == 0) and np.all(r.cumulative_bound_m == 0):
            assert r.chain not in origins, (r.chain, origins[r.chain], r.cycle.cycle)
            origins[r.chain] = r.cycle.cycle
    assert origins == {0: 1, 1: 7}
    assert np.all(np.isnan(by_cycle[6].cumulative_m)) and by_cycle[6].chain == 1
    for r in rows:  # every trusted cumulative counts from its chain's origin
        if r.displacement.status == "ok" and np.all(np.isfinite(r.cumulative_m)):
            np.testing.assert_allclose(r.cumulative_m[:2], (rigs[r.cycle.cycle] - rigs[origins[r.chain]])[:2],
                                       atol=0.02)


def test_a_restart_after_cycles_without_archives_names_them(caplog):
    """'no trusted match for 4 cycles' read as four failed cycles when two had no archive (indepZa F6); they
    may also have had archives none of which could be used (errors.csv says which)."""
    cycles, _ = noisy_cycles(12, seed=3)
    cycles = [dataclasses.replace(c, plates=[]) if c.cycle == 4 else c
              for c in cycles if c.cycle not in (5, 6)]
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        chain.rig_series(cycles, PRIOR)
    words = ("no trusted match for 4 cycles up to cycle 7 (since cycle 3; not in the series, no archive or "
             "none usable: 5, 6)")
    assert words in caplog.text


def test_a_live_chain_keeps_a_bounded_state_over_hundreds_of_cycles():
    """Rows, covariances, histories and the witnesses of the learned step stay bounded (indepZg F4)."""
    cycles, _ = noisy_cycles(300, seed=9, webs_m=np.full(300, 0.15))
    live_chain = chain.RigChain(dataclasses.replace(BLIND, motion_model=False))  # witnesses consulted often
    sizes = []
    for c in cycles:
        live_chain.add(c)
        live_chain.forget()
        sizes.append((len(live_chain.rows), len(live_chain._covs),
                      sum(len(v) for v in live_chain._forgotten_steps.values()), len(live_chain._steps)))
    late = np.array(sizes[100:])
    assert late[:, 0].max() <= 2 * (chain.LEARN_PAIRS + chain.DEFAULT_MAX_BRIDGE_CYCLES)
    assert late[:, 1].max() <= 2 * (chain.LEARN_PAIRS + chain.DEFAULT_MAX_BRIDGE_CYCLES)
    assert late[:, 2].max() <= 2 * chain.WITNESS_HISTORY and late[:, 3].max() <= chain.MOTION_HISTORY
