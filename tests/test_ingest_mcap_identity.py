"""MCAP identity and numbers: a channel is one publisher of one topic, never merged with another; JSON
numbers that are not finite never become data. Each log is written by the ``mcap`` package's Writer from a
known drive, and the counts and values read back are compared with what was written."""
import json
import math
import struct
import warnings

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from calib.errors import LogFormatError
from calib.ingest import read_streams
from testcars.fabricate import fabricate_streams
from calib.ingest.writers import write_streams


def _read(path, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s, m = read_streams(path, **kw)
    return s, m, [str(w.message) for w in caught]


def test_known_drive_reads_back_with_every_sample_accounted(tmp_path):
    streams, meta = fabricate_streams(120, seed=3)
    p = write_streams(streams, meta, tmp_path / "d.mcap", "mcap")
    s, m, said = _read(p)
    assert not m.damage and not said
    t0 = min(x.index[0] for x in streams.values())
    for ch, ref in streams.items():
        assert m.channel_counts[ch] == {"read": len(ref), "nonfinite": 0, "out_of_range": 0, "merged": 0,
                                        "kept": len(ref)}, ch
        np.testing.assert_allclose(s[ch].index, ref.index - t0, atol=1e-6)
        np.testing.assert_allclose(s[ch].to_numpy(), ref.to_numpy(), rtol=1e-12, atol=1e-12)


def _two_publishers(path, compression=CompressionType.ZSTD):
    """/engine published on two channels (two schemas, two rates), /vehicle/speed on one. Returns the
    channel ids and what each /engine channel carried: {id: (times, rpm)}."""
    sent = {}
    with open(path, "wb") as fh:
        w = Writer(fh, compression=compression)
        w.start()
        sa = w.register_schema(name="ecu.A", encoding="jsonschema", data=b"{}")
        sb = w.register_schema(name="obd.B", encoding="jsonschema", data=b"{}")
        a = w.register_channel(topic="/engine", message_encoding="json", schema_id=sa)
        v = w.register_channel(topic="/vehicle/speed", message_encoding="json", schema_id=sa)
        b = w.register_channel(topic="/engine", message_encoding="json", schema_id=sb)
        events = []
        for cid, rate, rpm in ((a, 10, 1000.0), (b, 2, 2500.0)):
            t = np.arange(0, 20, 1 / rate)
            sent[cid] = (t, rpm + 10 * t)
            events += [(tk, cid, {"speed": rpm + 10 * tk}) for tk in t]
        events += [(tk, v, {"speed": 0.5 * tk}) for tk in np.arange(0, 20, 0.1)]
        events.sort(key=lambda e: (e[0], e[1]))
        for seq, (tk, cid, obj) in enumerate(events):
            ns = int(round(tk * 1e9))
            w.add_message(cid, log_time=ns, data=json.dumps(obj).encode(), publish_time=ns, sequence=seq)
        w.finish()
    return a, b, sent


def test_two_channels_on_one_topic_are_refused_by_name(tmp_path):
    a, b, _ = _two_publishers(tmp_path / "two.mcap")
    with pytest.raises(LogFormatError) as e:
        read_streams(tmp_path / "two.mcap")
    text = str(e.value)
    assert f"topic /engine is published on 2 channels (id {a}: schema 'ecu.A'" in text
    assert f"id {b}: schema 'obd.B'" in text and "200 messages" in text and "40 messages" in text
    assert f"'/engine#{b}'" in text and "not merged" in text


@pytest.mark.parametrize("pick", [0, 1])
def test_topic_hash_channel_reads_that_channel_only(tmp_path, pick):
    a, b, sent = _two_publishers(tmp_path / "two.mcap", CompressionType.LZ4)
    cid = (a, b)[pick]
    other = (a, b)[1 - pick]
    s, m, _ = _read(tmp_path / "two.mcap", topic_map={f"/engine#{cid}": {"speed": "engine_speed_rpm [rpm]"}})
    t, rpm = sent[cid]
    assert m.channel_counts["engine_speed_rpm"]["read"] == len(t) == m.channel_counts["engine_speed_rpm"]["kept"]
    np.testing.assert_allclose(s["engine_speed_rpm"].to_numpy(), rpm)
    np.testing.assert_allclose(s["engine_speed_rpm"].index, t, atol=1e-6)
    assert m.channel_sources["engine_speed_rpm"] == f"/engine#{cid}.speed"
    assert len(s["speed_mps"]) == 200  # the default map's other topics stay
    said = [n for n in m.notes if n.startswith("topic /engine")]
    assert len(said) == 1 and f"id {other}:" in said[0] and f"reads channel {cid}" in said[0]


def test_topic_hash_channel_on_another_topic_is_an_error(tmp_path):
    a, b, _ = _two_publishers(tmp_path / "two.mcap")
    with pytest.raises(LogFormatError, match=rf"'/engine#{a + 1}' names channel {a + 1}, which is on topic "
                                             r"'/vehicle/speed'"):
        read_streams(tmp_path / "two.mcap", topic_map={f"/engine#{a + 1}": {"speed": "engine_speed_rpm [rpm]"}})


def test_channel_id_defined_twice_drops_its_later_messages(tmp_path):
    """A channel record reusing an id with another topic: messages on that id after it are ambiguous."""
    p = tmp_path / "redef.mcap"
    with open(p, "wb") as fh:
        w = Writer(fh, use_chunking=False, repeat_channels=False, repeat_schemas=False)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        c1 = w.register_channel(topic="/vehicle/speed", message_encoding="json", schema_id=sid)
        for k in range(5):
            w.add_message(c1, log_time=k * 10**9, data=json.dumps({"speed": float(k)}).encode(), publish_time=0)
        c2 = w.register_channel(topic="/environment", message_encoding="json", schema_id=sid)
        for k in range(5, 10):
            w.add_message(c1, log_time=k * 10**9, data=json.dumps({"speed": float(k)}).encode(), publish_time=0)
        w.finish()
    data = bytearray(p.read_bytes())
    topic = b"/environment"
    k = data.find(struct.pack("<HHI", c2, sid, len(topic)) + topic)  # channel record: id, schema id, topic
    assert k > 0 and data.count(topic) == 1
    data[k:k + 2] = struct.pack("<H", c1)  # the second channel record now claims the first one's id
    p.write_bytes(bytes(data))
    s, m, said = _read(p)
    np.testing.assert_allclose(s["speed_mps"].to_numpy(), np.arange(5.0))
    assert m.damage["pieces_lost"] == 6
    assert f"channel id {c1} defined twice, as '/vehicle/speed' (json) and '/environment' (json)" in said[0]
    with pytest.raises(LogFormatError, match=f"channel id {c1} defined twice"):
        read_streams(p, strict=True)


def test_non_finite_json_numbers_are_dropped_and_counted(tmp_path):
    """Python's json reads Infinity, NaN and 1e400 as floats (and 10**400 as an int no float holds)."""
    p = tmp_path / "nf.mcap"
    bad_at = {3: b"Infinity", 7: b"-Infinity", 11: b"NaN", 15: b"1e400", 19: b"-" + b"9" * 400}
    with open(p, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        c = w.register_channel(topic="/engine", message_encoding="json", schema_id=sid)
        for k in range(25):
            rpm = bad_at.get(k, str(800.0 + k).encode())
            data = b'{"speed": ' + rpm + b', "coolant_temp": ' + str(20.0 + k).encode() + b"}"
            w.add_message(c, log_time=k * 10**8, data=data, publish_time=0)
        w.finish()
    s, m, said = _read(p)
    good = [k for k in range(25) if k not in bad_at]
    np.testing.assert_allclose(s["engine_speed_rpm"].to_numpy(), 800.0 + np.array(good))
    np.testing.assert_allclose(s["engine_speed_rpm"].index, 0.1 * np.array(good), atol=1e-6)
    assert m.channel_counts["engine_speed_rpm"] == {"read": 25, "nonfinite": 5, "out_of_range": 0, "merged": 0,
                                                    "kept": 20}
    assert m.channel_counts["coolant_temp_degC"]["kept"] == 25  # the same messages' other field stays
    assert all(math.isfinite(x) for x in s["engine_speed_rpm"])
    assert not m.damage
    assert any("engine_speed_rpm" in w for w in said)  # the loss (20 %) is named


def test_a_field_that_is_not_a_number_loses_only_that_value(tmp_path):
    p = tmp_path / "str.mcap"
    with open(p, "wb") as fh:
        w = Writer(fh, compression=CompressionType.NONE)
        w.start()
        c = w.register_channel(topic="/engine", message_encoding="json", schema_id=0)
        for k in range(10):
            obj = {"speed": "n/a" if k == 4 else 900.0 + k, "coolant_temp": 30.0 + k}
            w.add_message(c, log_time=k * 10**9, data=json.dumps(obj).encode(), publish_time=0)
        w.finish()
    s, m, said = _read(p)
    assert len(s["engine_speed_rpm"]) == 9 and len(s["coolant_temp_degC"]) == 10
    assert m.damage["pieces_lost"] == 1 and m.damage["where"] == ["message 5 on /engine"]
    assert "field 'speed' is not a number" in said[0]
