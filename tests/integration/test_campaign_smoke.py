"""A small feature-level wind campaign in CI (issue 14 item 6), on two worker processes.

20 runs per law and level (seed 2026: other starts than the reference campaign's seed 14;
SPEC box, random horizontal wind direction, vertical x0.3 down, gusts 30 %), the paper's laws
and observer_integral (params.yaml's default since 2026-11-26; the observer before), at 0
and 0.5 m/s^2, through ``campaign.run_campaign`` with 2 workers. Measured (2026-11-25, commit
e05fceb): paper 20 / 20 at 0 and 1 / 20 at 0.5 m/s^2 (observer 20 / 20 and 20 / 20;
clearance min 13.6 cm, landing error p95 2.5 cm, touchdown p95 0.28 m/s at 0.5); 30 runs each
took 97 s at load average 7 (2 / 30 for paper at 0.5); these 20 took 57 s at load average 5.3
(~27 s expected idle).

Bound: this sample agrees with a reference campaign (seed 14, 86 runs per law and level;
``REFERENCES`` below) when their 95 % Wilson intervals overlap. For a reference of 100 %
(interval [lo, 1]) that needs at least k of 20 with k the smallest count whose upper bound
reaches lo (lo = 95.7 % for 86 / 86 needs 18 / 20); the paper's 3 / 86 at 0.5 m/s^2
([1.2, 9.8] %) allows up to 4 / 20. The runs are deterministic, so this margin is for what
may legitimately move a few borderline runs (numerics of another numpy, a small retune), not
for chance; a change of the laws that moves a rate by more than the margin fails here and
must update these numbers.

Two estimate models, one case each (2026-11-28): ``exact`` (no attitude-estimate error, the
model issue 14's targets were set on; reference: docs/performance.md "Campaign" for the
paper, 30 / 30 and 30 / 30 for observer_integral, docs/design.md) and ``px4`` (params.yaml's
sim error, PX4 SIH's 0.7 deg / 2 s; reference s31-ref14: ``python -m ibvs_harness.campaign
--name s31-ref14 --seed 14 --runs 86 --levels 0 0.5 --law paper --law observer_integral
--workers 2``, 71 s, docs/design.md "A realistic estimate error"). This sample with the px4
model (18 s idle): paper 17 / 20 and 0 / 20, the default 20 / 20 and 20 / 20, landing error
p95 3.4 and 5.9 cm. Since the controller flies a loss of the pad on the centre carried by the
floor flow (2026-11-28, docs/design.md "The pad through a short loss"; reference s32-ref14,
the same command): paper 75 / 86 and 0 / 86, the default 86 / 86 and 84 / 86, landing error
p95 4.7 / 5.6 cm (6.1 cm before at 0.5 m/s^2); this sample: paper 19 / 20 and 0 / 20, the
default 20 / 20 and 20 / 20, p95 3.4 / 5.2 cm.
"""
import os

import pytest

from ibvs_harness.campaign import CampaignConfig, LawSpec, run_campaign, write_outputs
from ibvs_harness.campaign_stats import wilson_interval

pytestmark = pytest.mark.slow

RUNS = 20
# (successes, runs) of the seed-14 reference campaigns per (law, wind level m/s^2)
REFERENCES = {
    'exact': {('paper', 0.0): (86, 86), ('paper', 0.5): (3, 86),
              ('observer_integral', 0.0): (30, 30), ('observer_integral', 0.5): (30, 30)},
    'px4': {('paper', 0.0): (75, 86), ('paper', 0.5): (0, 86),
            ('observer_integral', 0.0): (86, 86), ('observer_integral', 0.5): (84, 86)},
}
ESTIMATE_NOISE = {'exact': (0.0, 2.0), 'px4': None}     # None: params.yaml's sim values
# issue 14's landing target (p95 <= 5 cm) per model and level; with PX4's estimate error it is
# still missed at 0.5 m/s^2 (5.6 cm in the reference, 5.2 here; 6.1 and 5.9 before the pad was
# carried through a loss): the slow lateral law near the floor and the level SHUTDOWN
# (docs/design.md, "Left open: the SHUTDOWN drift" and the paragraph after it)
LANDING_P95_M = {('exact', 0.0): 0.05, ('exact', 0.5): 0.05,
                 ('px4', 0.0): 0.05, ('px4', 0.5): 0.06}
DEFAULT_LAW = 'observer_integral'           # params.yaml's


@pytest.mark.parametrize('model', ['exact', 'px4'])
def test_small_campaign_agrees_with_the_reference(tmp_path, model):
    cfg = CampaignConfig(name='ci', runs=RUNS, levels_mps2=(0.0, 0.5), seed=2026,
                         laws=(LawSpec.parse('paper'), LawSpec.parse(DEFAULT_LAW)),
                         estimate_noise=ESTIMATE_NOISE[model], results_root=str(tmp_path))
    summaries = run_campaign(cfg, workers=2, progress=None)
    assert len(summaries) == 4 * RUNS
    rows = {(r['law'], r['wind_level_mps2']): r
            for r in write_outputs(cfg, summaries, plots=False)}
    for key, (k_ref, n_ref) in REFERENCES[model].items():
        r = rows[key]
        lo, hi = wilson_interval(r['successes'], r['runs'])
        ref_lo, ref_hi = wilson_interval(k_ref, n_ref)
        assert lo <= ref_hi and hi >= ref_lo, (key, r, (ref_lo, ref_hi))
    # the targets of issue 14 in every condition where the default law succeeds
    for level in (0.0, 0.5):
        r = rows[(DEFAULT_LAW, level)]
        assert r['clearance_min_m'] >= 0.05, r
        assert r['landing_error_p95_m'] <= LANDING_P95_M[model, level], r
        assert r['touchdown_speed_p95_mps'] <= 0.5, r
    assert os.path.exists(os.path.join(cfg.out_dir, 'table.md'))
    # resumable: nothing left to fly
    messages = []
    assert run_campaign(cfg, workers=2, progress=messages.append) == summaries
    assert messages == [f'campaign ci: {4 * RUNS} runs, {4 * RUNS} done, 0 to fly on 2 '
                        'worker(s)']
