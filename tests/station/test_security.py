"""The security matrix: every refused request with its status and error, none accepted; a
station that cannot keep keys off the network does not start; one whose devices are gone is
not healthy; TLS serves when configured."""

import json
import ssl
import subprocess
import time

import httpx
import pytest

from conftest import ROOT, SIM_RIG, Station, cli, timelapse


def test_the_matrix_refuses_every_bad_request(station):
    expired = station.key("expired", "admin", "--expires-in", "1s")
    revoked = station.key("revoked", "admin")
    cli("station", "key", "revoke", "--config", station.config, revoked["id"])
    time.sleep(1.2)
    good = station.keys["admin"]["key"]
    tampered = good[:-1] + ("0" if good[-1] != "0" else "1")
    cases = [
        ("missing key", {}, 401, "no API key"),
        ("not bearer", {"Authorization": f"Basic {good}"}, 401, "malformed"),
        ("malformed", {"Authorization": "Bearer pst_1234_abcd"}, 401, "malformed"),
        ("tampered", {"Authorization": f"Bearer {tampered}"}, 401, "not known"),
        ("expired", {"Authorization": f"Bearer {expired['key']}"}, 401, "expired"),
        ("revoked", {"Authorization": f"Bearer {revoked['key']}"}, 401, "revoked"),
        ("read scope", {"Authorization": f"Bearer {station.keys['read']['key']}"}, 403, "queue"),
    ]
    for what, headers, code, says in cases:
        r = httpx.post(station.url + "/api/v1/queue", json={"plan": timelapse()},
                       headers=headers, timeout=30)
        assert r.status_code == code, (what, r.status_code, r.text)
        assert says in r.json()["error"], (what, r.json())
    with station.client("queue") as c:
        assert c.post("/api/v1/run/abort").status_code == 403, "queue scope cannot control"
        big = {"plan": "#" * (300 * 1024)}
        r = c.post("/api/v1/queue", json=big)
        assert r.status_code == 413 and "body" in r.json()["error"], r.text
        for bad_id in ["..%2F..%2Fetc%2Fpasswd", "-1", "1e3", "%00"]:
            r = c.delete(f"/api/v1/queue/{bad_id}")
            assert r.status_code in (400, 404), (bad_id, r.status_code, r.text)
            assert r.json().get("field") in ("id", None), r.text
        r = c.post("/api/v1/queue", json={"plan": timelapse().replace("exposure_us = 250", "exposure_us = -5")})
        assert r.status_code == 400 and r.json()["field"] == "plan" and "exposure_us" in r.json()["error"], r.text
        r = c.post("/api/v1/queue", json={"plan": timelapse() + '[simulation]\nscene = "/etc/passwd"\n'})
        assert r.status_code == 400 and "simulation.scene" in r.json()["error"], r.text
        cal = (ROOT / "examples" / "plans" / "calibrate_analyzer.toml").read_text()
        r = c.post("/api/v1/queue", json={"plan": cal})
        assert r.status_code == 400 and "rig file" in r.json()["error"], "calibrations stay local"
        r = c.post("/api/v1/queue", json={"plan": timelapse(),
                                          "schedule": {"sun_above_deg": 80}})
        assert r.status_code == 400 and r.json()["field"] == "schedule", "a window that never opens"
        r = c.post("/api/v1/queue", json={"plan": timelapse(), "priority": 5000})
        assert r.status_code == 400 and r.json()["field"] == "priority", r.text
        r = c.post("/api/v1/queue", json={"plan": timelapse(), "colour": 1})
        assert r.status_code == 400 and "colour" in r.json()["error"], r.text
        r = c.post("/api/v1/queue", content=b"{not json", headers={"content-type": "application/json"})
        assert r.status_code == 400, r.text
        assert c.get("/api/v1/queue").json()["items"] == [], "none accepted"
    # Repeated failures are slowed (100 ms more per failure in the last minute, 3 s at most).
    t0 = time.monotonic()
    httpx.get(station.url + "/api/v1/status", headers={"Authorization": f"Bearer {tampered}"}, timeout=30)
    assert time.monotonic() - t0 >= 0.5, "after a dozen failures an answer waits"
    # Refused writes are audited.
    audit = [json.loads(l) for l in (station.dir / "data" / "audit.log").read_text().splitlines()]
    assert sum(1 for a in audit if not a["ok"]) >= 7
    keys = (station.dir / "data" / "keys.json").read_text()
    assert good[17:] not in keys, "only hashes are stored"


def test_a_network_bind_without_tls_is_refused(tmp_path):
    st = Station(tmp_path)
    st.config.write_text(st.config.read_text().replace("127.0.0.1:0", "0.0.0.0:0"))
    p = cli("station", "serve", "--config", st.config, check=False, timeout=30)
    assert p.returncode == 2 and "listen" in p.stderr and "TLS" in p.stderr, p.stderr


def test_a_station_whose_devices_are_gone_is_not_healthy(tmp_path):
    rig = tmp_path / "rig.toml"
    text = SIM_RIG.read_text().replace('port = "sim"', 'port = "/dev/serial/by-id/gone-stage"')
    text = text.replace('file = "../cameras/', f'file = "{ROOT}/examples/cameras/')
    rig.write_text(text)
    st = Station(tmp_path)
    st.config.write_text(st.config.read_text().replace(str(SIM_RIG), str(rig)))
    st.start()
    try:
        r = httpx.get(st.url + "/healthz", timeout=30)
        assert r.status_code == 503 and not r.json()["devices"]["ok"], r.text
        p = cli("station", "health", "--url", st.url, check=False)
        assert p.returncode == 1
    finally:
        st.stop()


def test_tls_serves_with_the_configured_certificate(tmp_path):
    # A station's own CA and the station's certificate signed by it (rustls, like browsers,
    # refuses a CA certificate presented as the server's own).
    ca, ca_key = tmp_path / "ca.pem", tmp_path / "ca.key"
    cert, key, csr, ext = (tmp_path / n for n in ("cert.pem", "key.pem", "leaf.csr", "ext.cnf"))
    ext.write_text("subjectAltName=IP:127.0.0.1\nbasicConstraints=CA:FALSE\n")
    for args in (["req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj",
                  "/CN=station test CA", "-keyout", ca_key, "-out", ca],
                 ["req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=127.0.0.1",
                  "-keyout", key, "-out", csr],
                 ["x509", "-req", "-in", csr, "-CA", ca, "-CAkey", ca_key, "-CAcreateserial",
                  "-days", "1", "-extfile", ext, "-out", cert]):
        subprocess.run(["openssl", *map(str, args)], check=True, capture_output=True)
    st = Station(tmp_path, f'[tls]\ncert = "{cert}"\nkey = "{key}"\n')
    st.config.write_text(st.config.read_text().replace("127.0.0.1:0", "0.0.0.0:0"))
    st.key("admin", "admin")
    st.start()
    try:
        assert st.url.startswith("https://")
        url = st.url.replace("0.0.0.0", "127.0.0.1")
        r = httpx.get(url + "/api/v1/status", verify=ssl.create_default_context(cafile=str(ca)),
                      timeout=30,
                      headers={"Authorization": f"Bearer {st.keys['admin']['key']}"})
        assert r.status_code == 200 and "change_id" in r.json()
        with pytest.raises(httpx.HTTPError):
            httpx.get(url.replace("https://", "http://") + "/healthz", timeout=5)
        # The command line's client trusts the station's certificate given by --ca-file, and
        # refuses the station without it (not in Mozilla's roots).
        key_file = tmp_path / "admin.key"
        key_file.write_text(st.keys["admin"]["key"] + "\n")
        ok = cli("station", "status", "--url", url, "--key-file", key_file, "--ca-file", ca,
                 check=False)
        assert ok.returncode == 0 and "change_id" in ok.stdout, ok.stderr
        refused = cli("station", "status", "--url", url, "--key-file", key_file, check=False)
        assert refused.returncode == 2 and "certificate" in refused.stderr.lower(), refused.stderr
    finally:
        st.stop()


def test_one_station_per_data_directory(station):
    p = cli("station", "serve", "--config", station.config, check=False, timeout=30)
    assert p.returncode == 2 and "data_dir" in p.stderr and "in use" in p.stderr, p.stderr
    assert httpx.get(station.url + "/healthz").status_code == 200, "the first one is unharmed"
