//! The Station tab attached to a real station (polar-station's server on loopback, in this
//! process), driven by its labels with egui_kittest: it shows the running item and its
//! progress, the station's health and its latest product images, and its Pause and Abort
//! buttons act on the station's item (the station's history says so). The station's
//! instrument is a stand-in `Runner` that "runs" until asked to stop, so the test needs no
//! device: what is judged is the GUI as a client of the station's API.
#![allow(clippy::unwrap_used)]

use eframe::egui;
use egui_kittest::kittest::Queryable;
use egui_kittest::Harness;
use polar_gui::{App, Tab};
use polar_station::config::Config;
use polar_station::keys::{KeyStore, Scope};
use polar_station::runner::{Plane, Request, RunControl, RunEnd, Runner};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// An instrument that runs until asked to pause or abort (at most a minute), reporting
/// progress every 20 ms; its latest product is a ramp.
struct StandIn;

impl StandIn {
    fn go(control: &Arc<RunControl>) -> RunEnd {
        for frame in 0..3000u64 {
            if let Some(r) = control.take() {
                let state = match r {
                    Request::Pause => "paused",
                    Request::Abort => "aborted",
                };
                return RunEnd {
                    state: state.into(),
                    reason: Some("asked from the GUI".into()),
                    result: json!({}),
                };
            }
            control.event(json!({"kind": "progress", "frames_done": frame, "frames": 3000}));
            std::thread::sleep(Duration::from_millis(20));
        }
        RunEnd {
            state: "done".into(),
            reason: None,
            result: json!({}),
        }
    }
}

impl Runner for StandIn {
    fn check(&self, _plan_file: &Path) -> Result<Value, String> {
        Ok(json!({"plan": "stand-in", "kind": "capture", "bytes": 1000,
                  "forecast": {"frames": 3000, "sets": 1, "duration_s": 60.0, "notes": []}}))
    }
    fn run(&self, _plan: &Path, run_dir: &Path, c: &Arc<RunControl>) -> Result<RunEnd, String> {
        std::fs::create_dir_all(run_dir).map_err(|e| e.to_string())?;
        std::fs::write(run_dir.join("started"), b"").map_err(|e| e.to_string())?;
        Ok(Self::go(c))
    }
    fn resume(&self, _run_dir: &Path, c: &Arc<RunControl>) -> Result<RunEnd, String> {
        Ok(Self::go(c))
    }
    fn has_started(&self, run_dir: &Path) -> bool {
        run_dir.join("started").exists()
    }
    fn site(&self) -> Option<polar_station::schedule::SunSite> {
        None
    }
    fn simulated(&self) -> bool {
        true
    }
    fn latest_product(&self, _run_dir: &Path, _name: &str) -> Result<Plane, String> {
        Ok(Plane {
            width: 16,
            height: 12,
            set: 0,
            values: (0..16 * 12).map(|i| i as f32 / 192.0).collect(),
        })
    }
    fn devices(&self) -> Value {
        json!({"ok": true, "stage": "stand-in"})
    }
}

/// A station on a free loopback port; its URL and an admin key's file.
fn station(dir: &Path) -> (String, PathBuf) {
    let file = dir.join("station.toml");
    std::fs::write(
        &file,
        "listen = \"127.0.0.1:0\"\ndata_dir = \"data\"\nrig = \"none.toml\"\nreserve_mb = 1\n",
    )
    .unwrap();
    let config = Config::load(&file).unwrap();
    std::fs::create_dir_all(&config.data_dir).unwrap();
    let mut keys = KeyStore::load(&config.keys_file()).unwrap();
    let (_, key) = keys
        .create(vec![Scope::Admin], None, "gui test", 0)
        .unwrap();
    let key_file = dir.join("station.key");
    std::fs::write(&key_file, format!("{key}\n")).unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let served = polar_station::serve::serve(config, Arc::new(StandIn), |addr, _| {
            let _ = tx.send(addr);
        });
        if let Err(e) = served {
            panic!("the station stopped: {e}");
        }
    });
    let addr = rx.recv_timeout(Duration::from_secs(30)).unwrap();
    (format!("http://{addr}"), key_file)
}

fn step_until(h: &mut Harness<'static, App>, what: &str, done: impl Fn(&App) -> bool) {
    let t0 = Instant::now();
    while !done(h.state()) {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "waited a minute for {what}: {:?}",
            h.state().station.heard()
        );
        h.step();
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn history(url: &str, key_file: &Path) -> Vec<Value> {
    let c = polar_station::client::Client::new(url, Some(key_file), None).unwrap();
    c.get("/api/v1/history").unwrap()["items"]
        .as_array()
        .cloned()
        .unwrap_or_default()
}

#[test]
fn the_station_tab_follows_and_controls_the_stations_item() {
    let dir = tempfile::tempdir().unwrap();
    let (url, key_file) = station(dir.path());
    let client = polar_station::client::Client::new(&url, Some(&key_file), None).unwrap();
    let queued = client
        .post("/api/v1/queue", &json!({"plan": "name = \"a\"\n"}))
        .unwrap();
    assert_eq!(queued["ids"], json!([1]), "{queued}");

    let app = App::new(dir.path().join("runs"), None).unwrap();
    let mut h = Harness::builder()
        .with_size(egui::vec2(1280.0, 900.0))
        .build_ui_state(|ui, app: &mut App| app.show(ui), app);
    h.get_by_label("Station").click();
    h.run();
    h.state_mut().station.url = url.clone();
    h.state_mut().station.key_file = key_file.display().to_string();
    h.get_by_label("Attach").click();
    h.run();
    // The running item, its progress, the health and the three latest images.
    step_until(&mut h, "the running item and its images", |a| {
        let heard = a.station.heard();
        heard.status["current"]["phase"] == "running"
            && heard.status["live"]["progress"]["frames_done"].as_u64() > Some(0)
            && heard.health["ok"] == true
            && heard.images.len() == 3
    });
    h.run();
    h.get_by_label_contains("Item 1 (stand-in): running");
    h.get_by_label("Health: ok");
    h.get_by_label("Latest dolp");
    assert_eq!(h.state().station.heard().images[1].1.size, [16, 12]);

    h.get_by_label("Pause the station's run").click();
    h.run();
    step_until(&mut h, "the item paused", |a| {
        a.station.heard().status["current"]["phase"] == "paused"
    });
    h.get_by_label("Abort the station's run").click();
    h.run();
    step_until(&mut h, "the item aborted", |a| {
        a.station.heard().status["current"].is_null()
    });
    let items = history(&url, &key_file);
    assert_eq!(items.len(), 1, "{items:?}");
    assert_eq!(items[0]["exit"], "aborted", "{items:?}");
    // The tab stays usable: its label selector shows it.
    assert_eq!(h.state().tab(), Tab::Station);
}
