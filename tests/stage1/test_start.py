"""The linear regime's stage 1 (host/stage1/start.py): candidate schedules, the best kept."""


import numpy as np
import pytest

from octcl.host.stage1.solve import default_schedules, display, project
from octcl.host.stage1.projections import retrieve_field
from octcl.host.stage1.start import linear_start
from conftest import scanner_made_target


def test_linear_start_stops_trying_once_a_candidate_renders_every_aimed_level(official_data):
    """On an official scan (the scanner rendered it), the first candidate renders every level: the
    half-length one is left out; without the hinge fit both run, neither at every level."""
    from octcl.host.pipeline.target import read_target, target_scan

    levels = target_scan(read_target(official_data / "Scan_Exp2_Layers_A.png"))
    found = linear_start(levels, lambda rendered: 0.0, schedules=default_schedules(150), threads=1)
    assert [c["identical"] for c in found.candidates] == [1.0]
    assert [step["name"] for step in found.candidates[0]["steps"]][:2] == ["display", "project"]
    plain = linear_start(levels, lambda rendered: 0.0, threads=1,
                         schedules=(display(150) + project(100), display(75) + project(100)))
    assert len(plain.candidates) == 2 and max(c["identical"] for c in plain.candidates) < 1.0


def test_linear_start_keeps_the_best_scoring_candidate():
    levels = scanner_made_target(2)
    scores = iter([0.5, 0.9, 0.7])  # the second candidate (half the steps) scores best
    calls = []
    schedules = tuple(display(steps) + project(20) for steps in (10, 5, 20))
    found = linear_start(levels, lambda rendered: next(scores), schedules=schedules, threads=1,
                         progress=lambda step, steps: calls.append((step, steps)))
    assert [c["schedule"] for c in found.candidates] == ["display:10,project:20", "display:5,project:20",
                                                         "display:20,project:20"]
    assert [c["score"] for c in found.candidates] == [0.5, 0.9, 0.7]
    assert found.schedule == schedules[1] and found.clock_steps == 0 and found.threads == 1
    assert calls[-1] == (35 + 60, 35 + 60)
    # The chosen field is the second candidate's, as its steps made it.
    from octcl.host.stage1.display import fit_field

    again = retrieve_field(levels, iterations=20, initial=fit_field(levels, iterations=5, time_budget_s=None,
                                                                    threads=1).field)
    np.testing.assert_array_equal(found.field, again.field)


@pytest.mark.clock
def test_linear_start_leaves_out_candidates_the_budget_cannot_hold():
    levels = scanner_made_target(2)
    found = linear_start(levels, lambda rendered: float(np.mean(rendered == levels)),
                         schedules=default_schedules(400), time_budget_s=0.5, threads=1)
    assert len(found.candidates) == 1 and found.clock_steps >= 1
    display_record = found.candidates[0]["steps"][0]
    assert display_record["name"] == "display" and display_record["iterations"] < 400  # cut by its share


def test_least_norm_twin_drops_what_the_rendering_does_not_show():
    """A field with a component twice its own norm that the operator does not pass (X − A⁺A·X, X random)
    renders the same levels after :func:`least_norm_twin` at about half its norm relative to its rendering,
    near the field without that component; that one, already of least norm, keeps its norm."""
    from octcl.config import ScannerConfig
    from octcl.host.stage1.backend import NumpyBackend
    from octcl.host.stage1.start import least_norm_twin
    from octcl.render import Rendering

    config = ScannerConfig(depth_pixels=64, a_scans=64, xmax_um=384.0)
    backend = NumpyBackend(config, threads=1)
    operator = backend.operator
    rng = np.random.default_rng(3)

    def random_field():
        return rng.standard_normal(config.shape) + 1j * rng.standard_normal(config.shape)

    def relative_norm(field):
        return np.linalg.norm(field) / np.abs(operator.apply(field)).max()

    seen = operator.pseudo_inverse(operator.apply(random_field() * np.exp(-np.arange(64) / 20)[:, None]))
    unseen = random_field()
    unseen -= operator.pseudo_inverse(operator.apply(unseen))
    field = seen + 2 * unseen * np.linalg.norm(seen) / np.linalg.norm(unseen)
    twins = {}
    for name, start in (("field", field), ("seen", seen)):
        aim = Rendering.from_a_scans(operator.apply(start)).levels
        twin = twins[name] = least_norm_twin(start, aim, backend, iterations=1000)
        assert twin.identical == 1.0
        assert np.array_equal(Rendering.from_a_scans(operator.apply(twin.field)).levels, aim)
    assert relative_norm(twins["field"].field) < 0.6 * relative_norm(field)
    assert relative_norm(twins["field"].field) < 1.2 * relative_norm(seen)
    assert 0.9 < relative_norm(twins["seen"].field) / relative_norm(seen) < 1.05
