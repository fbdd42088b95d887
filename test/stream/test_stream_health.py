"""The intraop stream's health status: silence, rate, and a silence with matched publishers told apart."""

from liver_p2p_reg.stream.health import StreamHealth
from liver_p2p_reg.stream.outputs import OK, STALE


def test_a_silence_says_whether_publishers_are_matched():
    health = StreamHealth()
    # before any cloud: a camera that is not there and one whose data do not arrive read differently
    alone = health.status(10.0, 5.0, publishers=0)
    assert alone.level == STALE and alone.message == "no intraop data yet (/intraop/points)"
    assert alone.values["publishers"] == "0"
    matched = health.status(10.0, 5.0, publishers=1)
    assert matched.level == STALE and matched.message.endswith("; 1 publisher matched, nothing arrives")
    unknown = health.status(10.0, 5.0)
    assert "publishers" not in unknown.values and unknown.message == alone.message
    # clouds at 10 Hz: OK, the count is only a value
    for i in range(20):
        health.on_cloud(20.0 + 0.1 * i, 0, 0)
    flowing = health.status(22.0, 5.0, publishers=2)
    assert flowing.level == OK and flowing.values["publishers"] == "2" and "matched" not in flowing.message
    # then silence past stale_after_s with two publishers matched
    silent = health.status(30.0, 5.0, publishers=2)
    assert (
        silent.level == STALE and silent.message == "no intraop data for 8.1 s; 2 publishers matched, nothing arrives"
    )
    assert silent.values["silent_s"] == "8.1"
