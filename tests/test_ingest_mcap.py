"""MCAP reader: default topic map, custom maps, log-time order, metadata."""
import json

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from calib.errors import LogFormatError
from calib.ingest import DEFAULT_TOPIC_MAP, read_streams
from testcars.fabricate import fabricate_streams
from calib.ingest.writers import write_streams


def _mcap(path, messages, metadata=None):
    """messages: [(topic, t_s, dict)]"""
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        chans = {}
        for topic, t, obj in messages:
            if topic not in chans:
                chans[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            ns = int(round(t * 1e9))
            w.add_message(chans[topic], log_time=ns, data=json.dumps(obj).encode(), publish_time=ns)
        if metadata:
            w.add_metadata("iptm", metadata)
        w.finish()
    return path


def test_written_mcap_reads_back_with_default_map(tmp_path):
    streams, meta = fabricate_streams(30)
    p = write_streams(streams, meta, tmp_path / "d.mcap", "mcap")
    s, m = read_streams(p)
    assert m.synthetic and m.format == "mcap"
    assert set(s) == set(streams)
    for ch in streams:
        np.testing.assert_allclose(s[ch].index, streams[ch].index - streams["speed_mps"].index[0], atol=1e-6)
        np.testing.assert_allclose(s[ch].to_numpy(), streams[ch].to_numpy(), atol=1e-9)
    assert "/hv_battery" in DEFAULT_TOPIC_MAP


def test_custom_topic_map_with_nested_fields_and_units(tmp_path):
    msgs = [("/obd", t, {"vss": {"kph": 36.0 * t}, "ect_f": 32.0 + t}) for t in range(5)]
    p = _mcap(tmp_path / "o.mcap", msgs)
    tmap = {"/obd": {"vss.kph": "speed_mps [km/h]", "ect_f": "coolant_temp_degC [degF]"}}
    s, m = read_streams(p, topic_map=tmap)
    np.testing.assert_allclose(s["speed_mps"], 10.0 * np.arange(5))
    np.testing.assert_allclose(s["coolant_temp_degC"].iloc[0], 0.0, atol=1e-9)
    assert m.channel_sources["speed_mps"] == "/obd.vss.kph"


def test_small_disorder_sorted_and_noted_large_is_error(tmp_path):
    msgs = [("/vehicle/speed", t, {"speed": t}) for t in (0.0, 0.2, 0.1, 0.3)]
    s, m = read_streams(_mcap(tmp_path / "a.mcap", msgs))
    assert list(s["speed_mps"].index) == [0.0, 0.1, 0.2, 0.3]
    assert any("out of log-time order" in n for n in m.notes)
    msgs = [("/vehicle/speed", t, {"speed": 1.0}) for t in (0.0, 10.0, 2.0)]
    with pytest.raises(LogFormatError, match=r"message 3 on /vehicle/speed.*goes back"):
        read_streams(_mcap(tmp_path / "b.mcap", msgs), strict=True)


def test_unmapped_topics_and_bad_fields(tmp_path):
    with pytest.raises(LogFormatError, match="no topic matches"):
        read_streams(_mcap(tmp_path / "c.mcap", [("/foo", 0.0, {"a": 1})]))
    with pytest.raises(LogFormatError, match=r"message 1 on /vehicle/speed.*not a number"):
        read_streams(_mcap(tmp_path / "d.mcap", [("/vehicle/speed", 0.0, {"speed": "fast"})]), strict=True)
