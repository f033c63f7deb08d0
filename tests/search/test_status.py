"""The search's status enum: each name has a message and compares equal to its JSON value, so
optimizer.json files written before the enum read the same."""
import json

from vdo.search.status import Status


def test_status_values_messages_and_json():
    assert {s.value for s in Status} == {"converged", "max_steps", "feasible", "time_limit",
                                         "interrupted", "failed"}
    for s in Status:
        assert s == s.value and str(s) == s.value and len(s.message) > 10
        assert json.loads(json.dumps({"status": s})) == {"status": s.value}
    assert Status("time_limit").stopped and Status.INTERRUPTED.stopped
    assert not Status.CONVERGED.stopped
