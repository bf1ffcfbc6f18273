"""The one frame feeder (data/playback.py) and the playback flag's one name (issue 27, item 4)."""

from __future__ import annotations

import numpy as np
import pytest

from virus_nerf.data.playback import FrameFeeder, Playback
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


def test_the_feeder_releases_each_frame_once_in_time_order():
    """Rows 0..4 at times 10.4, 10.0, 10.0, 11.0, 10.2 s at speed 2: the clock starts at the first
    frame's time (10.0); after 0.1 s the recording reached 10.2, after 0.5 s 11.0."""
    feeder = FrameFeeder([10.4, 10.0, 10.0, 11.0, 10.2], speed=2.0)
    np.testing.assert_array_equal(feeder.release(0.0), [1, 2])  # both at 10.0, ties in row order
    assert feeder.wait(0.0) == pytest.approx(0.1)  # 10.2 is 0.2 s of recording away: 0.1 s at x2
    np.testing.assert_array_equal(feeder.release(0.1), [4])
    assert feeder.last_time == 10.2
    np.testing.assert_array_equal(feeder.release(0.1), [])  # nothing twice
    np.testing.assert_array_equal(feeder.due(0.2), [1, 2, 4, 0])  # every frame reached so far
    np.testing.assert_array_equal(feeder.release(0.5), [0, 3])
    assert feeder.done and feeder.wait(0.5) == float("inf") and feeder.last_time == 11.0
    np.testing.assert_array_equal(FrameFeeder([5.0]).due(0.0), [0])  # the first frame is due at once
    with pytest.raises(ValueError, match="at least one frame"):
        FrameFeeder([])


@pytest.mark.parametrize("speed", [0.0, -1.0, float("inf"), float("nan")])
def test_a_speed_that_is_not_positive_and_finite_is_refused(speed):
    with pytest.raises(ValueError, match="playback speed"):
        Playback(0.0, speed)


def test_the_old_flag_name_still_works_with_a_notice(capsys):
    from virus_nerf.errors import say_notes

    assert renamed_flag("--playback", None, "--playback-speed", 2.0) == 2.0
    assert capsys.readouterr().err == ""  # said once every argument is accepted
    say_notes()
    assert "--playback-speed is deprecated; use --playback" in capsys.readouterr().err
    say_notes()
    assert capsys.readouterr().err == ""  # once
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
    from virus_nerf.errors import PENDING_NOTES

    PENDING_NOTES.clear()  # the CLI drops them with the error (below)


@pytest.mark.parametrize("argv, named", [
    (["online", "--out", "{tmp}/o", "--playback-speed", "-3"], "--playback-speed -3.0: expected a number > 0"),
    (["train", "--data", "{tmp}", "--room", "office", "--out", "{tmp}/r", "--online", "--playback-speed", "2",
      "--max-steps", "-1"], "--max-steps"),
])
def test_a_refused_command_with_the_old_flag_prints_its_error_alone(tmp_path, argv, named):
    """A review: the deprecation note came before the error, two lines, naming --playback for a
    --playback-speed given. Now the error line alone, naming the flag given."""
    from helpers import run_cli
    from test_cli_errors import assert_one_line_error

    code, _, err = run_cli([a.format(tmp=tmp_path) for a in argv])
    assert_one_line_error(code, err, named)
