"""A damaged MDF4 channel layout is refused before asammdf reads it.

asammdf slices records in compiled code at the channel's byte offset: an offset pointing outside the record
reads foreign memory (the fuzz harness saw the process crash, or garbage come back). The reader checks the
layout of each channel and of its group's time channel first and skips what does not fit, with a warning."""
import struct
import warnings

import numpy as np
import pytest

from calib.errors import LogDamageWarning
from calib.ingest import read_log

asammdf = pytest.importorskip("asammdf")


def _write(path):
    t = np.arange(0.0, 8.0, 0.2)
    mdf = asammdf.MDF(version="4.10")
    mdf.append([asammdf.Signal(np.full_like(t, 30.0), t, name="speed", unit="km/h")])
    mdf.append([asammdf.Signal(np.linspace(-10, -9, t.size), t, name="ambient_temp", unit="degC")])
    mdf.save(path, overwrite=True)
    mdf.close()
    return path


def _patch_byte_offset(path, channel, value, master=False):
    """Write ``value`` into the cn_byte_offset field of a channel's CN block (or of its group's master)."""
    with asammdf.MDF(path) as m:
        gi, ci = m.channels_db[channel][0]
        grp = m.groups[gi]
        if master:
            ci = next(k for k, c in enumerate(grp.channels) if c.channel_type == 2)
        addr = grp.channels[ci].address
    data = bytearray(path.read_bytes())
    assert data[addr:addr + 4] == b"##CN"
    links = struct.unpack_from("<Q", data, addr + 16)[0]
    field = addr + 24 + 8 * links + 4  # cn_type, cn_sync_type, cn_data_type, cn_bit_offset, then cn_byte_offset
    struct.pack_into("<I", data, field, value)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("master", [False, True])
def test_channel_outside_its_record_is_skipped_with_a_warning(tmp_path, master):
    p = _write(tmp_path / "drive.mf4")
    intact = read_log(p).data
    _patch_byte_offset(p, "ambient_temp", 4104, master=master)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        log = read_log(p)
    msgs = [str(x.message) for x in w if issubclass(x.category, LogDamageWarning)]
    assert len(msgs) == 1 and "channel outside its record" in msgs[0]
    assert log.meta.damage["where"] == ["MDF channel 'ambient_temp'"]
    assert "ambient_temp_degC" not in log.data.columns
    # the intact channel comes back unchanged
    np.testing.assert_allclose(log.data["speed_mps"].to_numpy(), intact["speed_mps"].to_numpy())


def test_strict_refuses_the_damaged_layout(tmp_path):
    p = _write(tmp_path / "drive.mf4")
    _patch_byte_offset(p, "ambient_temp", 4104)
    with pytest.raises(Exception, match="outside its record"):
        read_log(p, strict=True)


def test_an_unclosed_handle_collected_during_a_read_is_not_damage_of_the_file(tmp_path, monkeypatch):
    """A ResourceWarning about some other object's unclosed file, emitted whenever the garbage collector
    runs inside the read, says nothing about this file: the intact file reads without any damage."""
    import asammdf as am

    p = _write(tmp_path / "drive.mf4")
    real_get = am.MDF.get

    def get_and_collect_a_leak(self, *a, **k):
        warnings.warn("unclosed file <_io.BufferedReader name='elsewhere.mf4'>", ResourceWarning, stacklevel=2)
        return real_get(self, *a, **k)

    monkeypatch.setattr(am.MDF, "get", get_and_collect_a_leak)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        log = read_log(p)
    assert not [x for x in w if issubclass(x.category, LogDamageWarning)]
    assert not log.meta.damage


def _patch_cycles(path, channel, cycles, record_bytes):
    """Write ``cycles`` and ``record_bytes`` into the CG block of a channel's group (cg_cycle_count, cg_data_bytes)."""
    with asammdf.MDF(path) as m:
        gi, _ = m.channels_db[channel][0]
        addr = m.groups[gi].channel_group.address
    data = bytearray(path.read_bytes())
    assert data[addr:addr + 4] == b"##CG"
    links = struct.unpack_from("<Q", data, addr + 16)[0]
    base = addr + 24 + 8 * links  # cg_record_id (8), cg_cycle_count (8), cg_flags (2), cg_path_separator (2),
    struct.pack_into("<Q", data, base + 8, cycles)  # 4 reserved, then cg_data_bytes (4), cg_inval_bytes (4)
    struct.pack_into("<I", data, base + 24, record_bytes)
    path.write_bytes(bytes(data))


def test_group_declaring_a_gigabyte_of_records_is_skipped_without_allocating_it(tmp_path):
    import resource

    p = _write(tmp_path / "drive.mf4")
    _patch_cycles(p, "ambient_temp", 393216, 1_003_487_232)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        log = read_log(p)
    grew_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    msgs = [str(x.message) for x in w if issubclass(x.category, LogDamageWarning)]
    assert len(msgs) == 1 and "group 1 declares 367488 GiB of records" in msgs[0] and "IPTM_MAX_INFLATE_MB" in msgs[0], msgs
    assert "ambient_temp_degC" not in log.data.columns and "speed_mps" in log.data.columns
    assert grew_mb < 200
