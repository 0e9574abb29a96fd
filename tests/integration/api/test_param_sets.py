"""Parameter sets: save from the device, compare, restore through the normal path."""

from __future__ import annotations

from urllib.parse import quote

from tests.support.servers import LiveServer


async def test_save_compare_restore(api: LiveServer) -> None:
    client = api.client
    await client.patch("/api/axes/line-0/params", json={"kp": 90, "kd": 200})
    response = await client.post("/api/axes/line-0/param-sets", json={"name": "stiff #1"})
    assert response.status_code == 201, response.text
    assert response.json()["params"]["kp"] == 90
    await client.patch("/api/axes/line-0/params", json={"kp": 30, "velocity": 3000})
    url = f"/api/axes/line-0/param-sets/{quote('stiff #1')}"
    comparison = (await client.get(f"{url}/compare")).json()
    assert comparison["differing"] == ["kp", "velocity"]
    assert comparison["device"]["kp"] == 30 and comparison["saved"]["kp"] == 90
    restored = (await client.post(f"{url}/restore")).json()
    assert restored["kp"] == 90 and restored["velocity"] == 2000
    assert api.bus.module(0).settings["kp"] == 90
    # Restoring is not persisting: the EEPROM still has the factory value until pg.
    sets = (await client.get("/api/axes/line-0/param-sets")).json()
    assert [s["name"] for s in sets] == ["stiff #1"]
    assert (await client.delete(url)).status_code == 204
    assert (await client.get("/api/axes/line-0/param-sets")).json() == []


async def test_bad_names_and_missing_sets(api: LiveServer) -> None:
    # Names a browser would fold away ("." and "..") or that cannot be told apart (" ")
    # could be saved once and then never opened: refused, naming the field.
    for name in ("a/b", ".", "..", " ", " a", "a ", "x" * 61):
        response = await api.client.post("/api/axes/line-0/param-sets", json={"name": name})
        assert response.status_code == 422, name
        assert response.json()["field"] == "name"
    response = await api.client.post("/api/axes/line-0/param-sets", json={"name": ".x. y"})
    assert response.status_code == 201, response.text
    url = f"/api/axes/line-0/param-sets/{quote('.x. y')}/compare"
    assert (await api.client.get(url)).status_code == 200
    response = await api.client.post("/api/axes/line-0/param-sets/nope/restore")
    assert response.status_code == 404
