"""The recorder process's core: a frame it cannot encode is counted, never fatal."""

from __future__ import annotations

from pathlib import Path

from appliance.recording.child import RecorderCore
from appliance.recording.files import FileSetParams, RecordingFiles
from appliance.recording.reader import RecordingReader

GB = 10**9


def test_a_frame_that_cannot_be_encoded_is_counted_and_the_rest_recorded(tmp_path: Path) -> None:
    params = FileSetParams(tmp_path, GB, 3600 * 10**9, 100 * GB, 0, 0, 10**9)
    core = RecorderCore(RecordingFiles(params, {}, lambda: "20240301T120000Z", lambda _: 100 * GB))
    core.handle(("cycle", 1, 0.5))  # a cycle without its inputs and output
    core.handle(("sample", 2, "odd.topic", 2, 0.6, {"fine": 1.5}))
    core.handle(("no such kind", 3))
    core.handle(())
    core.files.close()
    assert core.bad_frames == 3
    (path,) = tmp_path.glob("*.mcap")
    messages = RecordingReader(path).read_all()
    assert [m.topic for m in messages] == ["/dbw/topic/odd.topic"]
    assert messages[0].json() == {"seq": 2, "stamp_s": 0.6, "value": {"fine": 1.5}}
