"""Rigs keep their amplifier's channel map: set, changed, removed with {}, admin only."""

from __future__ import annotations

from tests.api.conftest import Api


def test_a_rig_keeps_its_channel_map(api: Api) -> None:
    admin = api.as_("admin")
    created = api.client.post(
        "/api/v1/rigs", json={"name": "Rig A", "channel_map": {"A1": "Fp1"}}, headers=admin
    )
    assert created.status_code == 201, created.text
    rig = created.json()
    assert rig["channel_map"] == {"A1": "Fp1"}
    changed = api.client.patch(
        f"/api/v1/rigs/{rig['id']}", json={"channel_map": {"A1": "Fp1", "A2": "AF7"}}, headers=admin
    )
    assert changed.json()["channel_map"] == {"A1": "Fp1", "A2": "AF7"}
    untouched = api.client.patch(
        f"/api/v1/rigs/{rig['id']}", json={"location": "Room 2"}, headers=admin
    )
    assert untouched.json()["channel_map"] == {"A1": "Fp1", "A2": "AF7"}
    removed = api.client.patch(f"/api/v1/rigs/{rig['id']}", json={"channel_map": {}}, headers=admin)
    assert removed.json()["channel_map"] is None
    refused = api.client.patch(
        f"/api/v1/rigs/{rig['id']}", json={"channel_map": {"A1": ""}}, headers=admin
    )
    assert refused.status_code == 422
    assert refused.json()["detail"][0]["field"].startswith("channel_map")
    by_staff = api.client.patch(
        f"/api/v1/rigs/{rig['id']}", json={"channel_map": {"A1": "Fz"}}, headers=api.as_("staff")
    )
    assert by_staff.status_code == 403
