//! `station`: an unattended station (`station serve`), its keys (`station key create|revoke|
//! list`), and its client (`station status|submit|validate|queue|remove|move|start|stop|pause|
//! resume|abort|history|health`) over the station's HTTP API.

use super::output::{print_json, refused};
use clap::{Args, Subcommand};
use polar_station::client::Client;
use polar_station::keys::{parse_duration_s, KeyStore, Scope};
use polar_station::{Config, StationError};
use serde_json::{json, Value};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

/// `station`: its subcommands.
#[derive(Debug, Args)]
pub struct StationGroup {
    #[command(subcommand)]
    command: StationCommand,
}

#[derive(Debug, Subcommand)]
enum StationCommand {
    /// Run the station: the rig, the queue, the API (loopback unless [tls] is configured);
    /// resumes the run a power cut interrupted. Prints {"listening": URL} when it is ready.
    Serve(ServeArgs),
    /// The station's API keys: create (shown once), revoke, list.
    Key(KeyGroup),
    /// The station's state: the queue, the current item and its progress.
    Status(ClientArgs),
    /// Health: devices, disk, clock, queue, last error (exit 1 when unhealthy; no key needed).
    Health(ClientArgs),
    /// Queue plan files (several: one batch, all or nothing); prints their ids.
    Submit(SubmitArgs),
    /// Check plan files as the station would queue them (the forecast), queuing nothing.
    Validate(SubmitArgs),
    /// The queued items.
    Queue(ClientArgs),
    /// Remove a queued item (or the paused current item, which leaves as stopped).
    Remove(IdArgs),
    /// Move a queued item to a position (0: next).
    Move(MoveArgs),
    /// Start taking items from the queue.
    Start(ClientArgs),
    /// Take no new item after the current one.
    Stop(ClientArgs),
    /// Pause the running item at its next set boundary.
    Pause(ClientArgs),
    /// Resume the paused item.
    Resume(ClientArgs),
    /// Abort the current item (what was acquired stays).
    Abort(ClientArgs),
    /// Items that left the station, with exit states and run directories.
    History(HistoryArgs),
}

impl StationGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        match self.command {
            StationCommand::Serve(a) => a.run(),
            StationCommand::Key(g) => g.run(),
            StationCommand::Health(a) => health(&a),
            StationCommand::Status(a) => call(&a, |c| c.get("/api/v1/status")),
            StationCommand::Submit(a) => a.send("/api/v1/queue"),
            StationCommand::Validate(a) => a.send("/api/v1/queue/validate"),
            StationCommand::Queue(a) => call(&a, |c| c.get("/api/v1/queue")),
            StationCommand::Remove(a) => {
                call(&a.client, |c| c.delete(&format!("/api/v1/queue/{}", a.id)))
            }
            StationCommand::Move(a) => call(&a.client, |c| {
                c.post(
                    &format!("/api/v1/queue/{}/move", a.id),
                    &json!({"position": a.position}),
                )
            }),
            StationCommand::Start(a) => call(&a, |c| c.post("/api/v1/queue/start", &json!({}))),
            StationCommand::Stop(a) => call(&a, |c| c.post("/api/v1/queue/stop", &json!({}))),
            StationCommand::Pause(a) => call(&a, |c| c.post("/api/v1/run/pause", &json!({}))),
            StationCommand::Resume(a) => call(&a, |c| c.post("/api/v1/run/resume", &json!({}))),
            StationCommand::Abort(a) => call(&a, |c| c.post("/api/v1/run/abort", &json!({}))),
            StationCommand::History(a) => call(&a.client, |c| {
                c.get(&match a.limit {
                    Some(n) => format!("/api/v1/history?limit={n}"),
                    None => "/api/v1/history".into(),
                })
            }),
        }
    }
}

/// `station serve`.
#[derive(Debug, Args)]
pub struct ServeArgs {
    /// The station file (TOML: listen, data_dir, rig, reserve_mb, ...; docs/STATION.md).
    #[arg(long)]
    config: PathBuf,
    /// Listen here instead of the file's `listen` (ADDR:PORT; port 0 picks a free one).
    #[arg(long)]
    listen: Option<String>,
}

impl ServeArgs {
    fn run(self) -> ExitCode {
        let started = (|| -> Result<(), StationError> {
            let mut config = Config::load(&self.config)?;
            if let Some(l) = &self.listen {
                config.listen =
                    polar_station::config::parse_listen(l).map_err(|m| StationError::Config {
                        file: "--listen".into(),
                        key: "listen".into(),
                        message: m,
                    })?;
            }
            config.check_bind()?;
            let runner = polar_cli::station_runner::CliRunner::new(&config.rig, config.auto_resume)
                .map_err(|m| StationError::Config {
                    file: self.config.display().to_string(),
                    key: "rig".into(),
                    message: m,
                })?;
            polar_station::serve::serve(config, Arc::new(runner), |addr, c| {
                let scheme = if c.tls.is_some() { "https" } else { "http" };
                // Whoever started the station may have stopped reading: never a panic.
                let _ = print_json(Ok::<_, StationError>(
                    json!({"listening": format!("{scheme}://{addr}"),
                           "data_dir": c.data_dir.display().to_string(),
                           "rig": c.rig.display().to_string()}),
                ));
            })
        })();
        match started {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => refused(e),
        }
    }
}

/// `station key`.
#[derive(Debug, Args)]
pub struct KeyGroup {
    #[command(subcommand)]
    command: KeyCommand,
}

#[derive(Debug, Subcommand)]
enum KeyCommand {
    /// Make a key (32 random bytes); prints it once: only its hash is kept.
    Create(KeyCreateArgs),
    /// Revoke a key by its id.
    Revoke(KeyRevokeArgs),
    /// The keys' ids, scopes, expiry and notes (never the keys).
    List(KeyConfigArgs),
}

#[derive(Debug, Args)]
struct KeyConfigArgs {
    /// The station file (the keys live in its data directory).
    #[arg(long)]
    config: PathBuf,
}

#[derive(Debug, Args)]
struct KeyCreateArgs {
    #[command(flatten)]
    config: KeyConfigArgs,
    /// What the key may do: read, queue, control, admin (comma-separated).
    #[arg(long, value_delimiter = ',', required = true)]
    scope: Vec<String>,
    /// Its lifetime (30d, 12h, 90m); default: until revoked.
    #[arg(long)]
    expires_in: Option<String>,
    /// Who holds it and what for.
    #[arg(long, default_value = "")]
    note: String,
    /// Write the key to this new file (mode 600) for --key-file, instead of printing it.
    #[arg(long)]
    key_out: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct KeyRevokeArgs {
    #[command(flatten)]
    config: KeyConfigArgs,
    /// The key's id (`station key list`).
    id: String,
}

impl KeyGroup {
    fn run(self) -> ExitCode {
        let keys_of = |c: &KeyConfigArgs| -> Result<KeyStore, StationError> {
            let config = Config::load(&c.config)?;
            std::fs::create_dir_all(&config.data_dir)
                .map_err(|e| StationError::io(&config.data_dir, e))?;
            KeyStore::load(&config.keys_file())
        };
        let now = polar_station::now_unix();
        let result = match self.command {
            KeyCommand::Create(a) => (|| {
                let scopes = a
                    .scope
                    .iter()
                    .map(|s| Scope::parse(s))
                    .collect::<Result<Vec<_>, _>>()?;
                let expires = a.expires_in.as_deref().map(parse_duration_s).transpose()?;
                let mut keys = keys_of(&a.config)?;
                if let Some(out) = &a.key_out {
                    if out.exists() {
                        return Err(StationError::Key(format!(
                            "--key-out {}: the file exists; a key is never overwritten",
                            out.display()
                        )));
                    }
                }
                let (rec, key) = keys.create(scopes, expires, &a.note, now)?;
                let mut v = json!({"id": rec.id, "scopes": rec.scopes,
                                   "expires": rec.expires_unix.map(polar_station::rfc3339)});
                match &a.key_out {
                    Some(out) => {
                        polar_station::atomic::write(out, format!("{key}\n").as_bytes(), true)?;
                        v["key_file"] = json!(out.display().to_string());
                    }
                    None => {
                        v["key"] = json!(key);
                        v["note"] = json!(
                            "shown once: only its hash is kept. Save it to a \
                                           file (chmod 600) for --key-file"
                        );
                    }
                }
                Ok(v)
            })(),
            KeyCommand::Revoke(a) => keys_of(&a.config)
                .and_then(|mut k| k.revoke(&a.id, now))
                .map(|()| json!({"revoked": a.id})),
            KeyCommand::List(a) => keys_of(&a).map(|k| {
                json!(k
                    .keys
                    .iter()
                    .map(|r| json!({
                        "id": r.id, "scopes": r.scopes, "note": r.note,
                        "created": polar_station::rfc3339(r.created_unix),
                        "expires": r.expires_unix.map(polar_station::rfc3339),
                        "revoked": r.revoked_unix.map(polar_station::rfc3339),
                    }))
                    .collect::<Vec<_>>())
            }),
        };
        print_json(result)
    }
}

/// Where the station is and the key to use.
#[derive(Debug, Args)]
pub struct ClientArgs {
    /// The station's address.
    #[arg(long, default_value = "http://127.0.0.1:8750")]
    url: String,
    /// A file holding the API key (`station key create` prints it once).
    #[arg(long)]
    key_file: Option<PathBuf>,
    /// For an https:// station: the certificate (PEM) to trust, e.g. its self-signed one;
    /// default Mozilla's roots.
    #[arg(long)]
    ca_file: Option<PathBuf>,
}

fn call(a: &ClientArgs, f: impl FnOnce(&Client) -> Result<Value, StationError>) -> ExitCode {
    print_json(Client::new(&a.url, a.key_file.as_deref(), a.ca_file.as_deref()).and_then(|c| f(&c)))
}

fn health(a: &ClientArgs) -> ExitCode {
    match Client::new(&a.url, None, a.ca_file.as_deref()).and_then(|c| c.get("/healthz")) {
        Ok(v) => {
            let healthy = v["ok"].as_bool() == Some(true);
            let printed = print_json(Ok::<_, StationError>(v));
            if healthy {
                printed
            } else {
                ExitCode::FAILURE
            }
        }
        Err(e) => refused(e),
    }
}

/// `station submit|validate PLAN...`.
#[derive(Debug, Args)]
pub struct SubmitArgs {
    #[command(flatten)]
    client: ClientArgs,
    /// Plan files (TOML or YAML, by extension).
    #[arg(required = true)]
    plans: Vec<PathBuf>,
    /// Higher runs first (-1000 to 1000).
    #[arg(long, default_value_t = 0, allow_negative_numbers = true)]
    priority: i32,
    /// Wait until the items leave the station; print their history entries (exit 1 unless
    /// every one is done).
    #[arg(long)]
    wait: bool,
}

impl SubmitArgs {
    fn send(&self, path: &str) -> ExitCode {
        let body = (|| -> Result<Value, StationError> {
            let mut items = Vec::new();
            for p in &self.plans {
                let text = std::fs::read_to_string(p).map_err(|e| StationError::io(p, e))?;
                let yaml = p.extension().is_some_and(|e| e == "yaml" || e == "yml");
                items.push(
                    json!({"plan": text, "format": if yaml { "yaml" } else { "toml" },
                                  "priority": self.priority}),
                );
            }
            Ok(json!({ "items": items }))
        })();
        if !self.wait || path.ends_with("/validate") {
            return call(&self.client, |c| c.post(path, &body?));
        }
        let client = match Client::new(
            &self.client.url,
            self.client.key_file.as_deref(),
            self.client.ca_file.as_deref(),
        ) {
            Ok(c) => c,
            Err(e) => return refused(e),
        };
        let waited = body
            .and_then(|b| client.post(path, &b))
            .and_then(|added| wait_for(&client, &added));
        match waited {
            Ok(entries) => {
                let all_done = entries.iter().all(|e| e["exit"] == "done");
                let printed = print_json(Ok::<_, StationError>(json!({ "items": entries })));
                if all_done {
                    printed
                } else {
                    ExitCode::FAILURE
                }
            }
            Err(e) => refused(e),
        }
    }
}

/// Polls the history until every id `added` names is in it; their entries.
fn wait_for(client: &Client, added: &Value) -> Result<Vec<Value>, StationError> {
    let ids: Vec<u64> = added["ids"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_u64).collect())
        .unwrap_or_default();
    loop {
        let history = client.get("/api/v1/history")?;
        let entries: Vec<Value> = history["items"]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter(|e| e["item"]["id"].as_u64().is_some_and(|id| ids.contains(&id)))
                    .cloned()
                    .collect()
            })
            .unwrap_or_default();
        if entries.len() == ids.len() {
            return Ok(entries);
        }
        // An item removed from the queue never reaches the history: say so, do not wait on.
        let queue = client.get("/api/v1/queue")?;
        let at_station = |id: u64| {
            queue["items"]
                .as_array()
                .is_some_and(|a| a.iter().any(|i| i["id"].as_u64() == Some(id)))
                || queue["current"]["item"]["id"].as_u64() == Some(id)
        };
        let history_now = client.get("/api/v1/history")?;
        let done = |id: u64| {
            history_now["items"]
                .as_array()
                .is_some_and(|a| a.iter().any(|e| e["item"]["id"].as_u64() == Some(id)))
        };
        if let Some(gone) = ids.iter().find(|&&id| !at_station(id) && !done(id)) {
            return Err(StationError::Client(format!(
                "item {gone} left the queue without running (removed): nothing to wait for"
            )));
        }
        std::thread::sleep(std::time::Duration::from_millis(500));
    }
}

/// `station remove ID`.
#[derive(Debug, Args)]
pub struct IdArgs {
    #[command(flatten)]
    client: ClientArgs,
    /// The item's id.
    id: u64,
}

/// `station move ID POSITION`.
#[derive(Debug, Args)]
pub struct MoveArgs {
    #[command(flatten)]
    client: ClientArgs,
    /// The item's id.
    id: u64,
    /// Its new position (0: next).
    position: usize,
}

/// `station history [--limit N]`.
#[derive(Debug, Args)]
pub struct HistoryArgs {
    #[command(flatten)]
    client: ClientArgs,
    /// The newest N entries only.
    #[arg(long)]
    limit: Option<usize>,
}
