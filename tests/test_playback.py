"""The one frame feeder (data/playback.py) and the playback flag's one name (issue 27, item 4)."""

from __future__ import annotations

import numpy as np
import pytest

from virus_nerf.data.playback import Playback
from virus_nerf.errors import UsageError, renamed_flag


def test_a_frame_is_due_once_elapsed_times_speed_passes_its_time():
    feeder = Playback(t0=100.0, speed=2.0)
    times = np.array([100.0, 100.5, 101.0, 103.0])
    # 0.3 s at x2 reach 100.6: the first two frames; 0.5 s reach 101.0 (a frame at it counts)
    np.testing.assert_array_equal(feeder.due(times, 0.3), [True, True, False, False])
    np.testing.assert_array_equal(feeder.due(times, 0.5), [True, True, True, False])
    assert feeder.recording_time(1.25) == pytest.approx(102.5)
    assert feeder.elapsed_at(103.0) == pytest.approx(1.5)  # (103 - 100) / 2
    assert feeder.elapsed_at(feeder.recording_time(0.7)) == pytest.approx(0.7)


@pytest.mark.parametrize("speed", [0.0, -1.0, float("inf"), float("nan")])
def test_a_speed_that_is_not_positive_and_finite_is_refused(speed):
    with pytest.raises(ValueError, match="playback speed"):
        Playback(0.0, speed)


def test_the_old_flag_name_still_works_with_a_notice(capsys):
    assert renamed_flag("--playback", None, "--playback-speed", 2.0) == 2.0
    assert "--playback-speed is deprecated; use --playback" in capsys.readouterr().err
    assert renamed_flag("--playback", 0.5, "--playback-speed", None) == 0.5
    assert capsys.readouterr().err == ""
    with pytest.raises(UsageError, match="--playback-speed 2.0: the old name of --playback"):
        renamed_flag("--playback", 0.5, "--playback-speed", 2.0)


def test_train_takes_the_old_flag_into_the_same_config_field(tmp_path, capsys):
    from virus_nerf.trainer.command import _resolve_config, train, train_flags

    given, flags = train_flags({"max_steps": 5, "online": True}, playback_speed=2.0)
    cfg = _resolve_config(None, given, flags)
    assert cfg.playback_speed == 2.0 and cfg.online
    with pytest.raises(UsageError, match="--playback-speed 0.0: expected a finite number > 0"):
        train(out=tmp_path / "run", data=tmp_path, room="office", knobs={"online": True}, playback_speed=0.0)
    assert "--playback-speed is deprecated" in capsys.readouterr().err
