"""``psctl cluster``'s tables, from a cluster view as the registry's ``cluster`` property gives it."""

from __future__ import annotations

from clients.cluster_view import device_rows, member_rows

VIEW = {
    "gateway": "gw-b",
    "members": [
        {"id": "gw-a", "address": "10.0.0.1:50051", "version": "0.1.0", "health": "ok", "owned": 0,
         "calls_per_s": 12.5, "listens": 3, "lease_expires": 1000.0, "draining": True, "read_only": ""},
        {"id": "gw-b", "address": "10.0.0.2:50051", "version": "", "health": "read-only", "owned": 7,
         "calls_per_s": 0.0, "listens": 0, "lease_expires": 0.0, "draining": False,
         "read_only": "etcd at 10.0.0.5:2379 cannot be reached"},
    ],
}  # fmt: skip


def test_each_gateway_is_a_row_with_its_state_load_and_lease_counted_from_now() -> None:
    header, a, b = member_rows(VIEW, now=997.5)
    assert header[:6] == ["GATEWAY", "ADDRESS", "VERSION", "HEALTH", "STATE", "OWNED"]
    assert a == ["gw-a", "10.0.0.1:50051", "0.1.0", "ok", "draining", "0", "12.5", "3", "+2.5s"]
    assert b == ["gw-b", "10.0.0.2:50051", "-", "read-only", "read-only", "7", "0", "0", "-"]
    # Every cell is one word: the table splits on spaces.
    assert all(" " not in cell for row in (a, b) for cell in row)


def test_devices_are_listed_by_name_with_owner_and_time_and_local_services_left_out() -> None:
    rows = device_rows({"thermo1": "gw-a", "registry": "", "rover2": "gw-b"}, {"thermo1": "0", "rover2": ""})
    assert [row[:2] for row in rows] == [["DEVICE", "OWNER"], ["rover2", "gw-b"], ["thermo1", "gw-a"]]
    assert rows[1][2] == "-" and rows[2][2] == "-"  # no time known
