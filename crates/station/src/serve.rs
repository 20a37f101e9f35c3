//! The long-lived process: binds (loopback, or anything with TLS), then starts the worker
//! (which first resumes the run a crash or power cut interrupted), serves the API until
//! SIGTERM or Ctrl-C, then pauses the going run at its next safe point so the next start
//! resumes it. One station per data directory (a lock on `data_dir/.lock`).

use crate::config::Config;
use crate::error::StationError;
use crate::runner::{Request, Runner};
use crate::shared::Station;
use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

/// How long a stop waits for the going run to reach a safe point.
const STOP_WAIT: Duration = Duration::from_secs(60);
/// How long open connections may take to finish once the station stops.
const DRAIN: Duration = Duration::from_secs(5);

/// Runs the station until it is told to stop. `on_listening` hears the bound address (with
/// port 0 in the file, the one the system picked) before the first request is taken.
pub fn serve(
    config: Config,
    runner: Arc<dyn Runner>,
    on_listening: impl FnOnce(SocketAddr, &Config),
) -> Result<(), StationError> {
    config.check_bind()?;
    if let Some(u) = &config.upload {
        // A bucket that cannot be set up (its secret file unreadable, say) stops the start,
        // rather than a station that would keep every run and never upload one.
        crate::upload::bucket(u)?;
    }
    let st = Station::open(config, runner)?;
    let addr = st.config.listen;
    let listener = std::net::TcpListener::bind(addr)
        .and_then(|l| l.set_nonblocking(true).map(|()| l))
        .map_err(|e| StationError::Serve(format!("cannot listen on {addr}: {e}")))?;
    let bound = listener.local_addr().unwrap_or(addr);
    if let Some(c) = st.snapshot().current {
        tracing::info!(
            "item {} ({}) was {:?} when the station stopped: taking it up again",
            c.item.id,
            c.item.name,
            c.phase
        );
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| StationError::Serve(format!("cannot start the async runtime: {e}")))?;
    let worker = crate::worker::spawn(st.clone())
        .map_err(|e| StationError::Serve(format!("cannot start the worker: {e}")))?;
    on_listening(bound, &st.config);
    // Uploads and retention; ends with the shutdown signal.
    let upkeep = rt.spawn(crate::upkeep::run(st.clone()));
    let served = rt.block_on(listen(st.clone(), listener));
    upkeep.abort();
    begin_stop(&st);
    stop(worker);
    served
}

async fn listen(st: Arc<Station>, listener: std::net::TcpListener) -> Result<(), StationError> {
    let app = crate::api::router(st.clone()).into_make_service_with_connect_info::<SocketAddr>();
    let signal = shutdown_signal(st.clone());
    let served = async {
        match st.config.tls.clone() {
            None => {
                let listener = tokio::net::TcpListener::from_std(listener)
                    .map_err(|e| StationError::Serve(e.to_string()))?;
                axum::serve(listener, app)
                    .with_graceful_shutdown(signal)
                    .await
                    .map_err(|e| StationError::Serve(e.to_string()))
            }
            Some(tls) => {
                let _ = rustls::crypto::aws_lc_rs::default_provider().install_default();
                let rustls =
                    axum_server::tls_rustls::RustlsConfig::from_pem_file(&tls.cert, &tls.key)
                        .await
                        .map_err(|e| {
                            StationError::Serve(format!(
                                "[tls] cert {} / key {}: {e}",
                                tls.cert.display(),
                                tls.key.display()
                            ))
                        })?;
                let handle = axum_server::Handle::new();
                let h = handle.clone();
                tokio::spawn(async move {
                    signal.await;
                    h.graceful_shutdown(Some(DRAIN));
                });
                axum_server::from_tcp_rustls(listener, rustls)
                    .handle(handle)
                    .serve(app)
                    .await
                    .map_err(|e| StationError::Serve(e.to_string()))
            }
        }
    };
    // Connections that do not finish (an event stream a client holds) get DRAIN after the
    // stop, not forever.
    let mut stopped = st.shutdown.subscribe();
    tokio::select! {
        r = served => r,
        _ = async {
            let _ = stopped.wait_for(|s| *s).await;
            tokio::time::sleep(DRAIN).await;
        } => Ok(()),
    }
}

/// Resolves at SIGTERM or Ctrl-C, after starting the stop (the going run asked to pause, the
/// event streams ended).
async fn shutdown_signal(st: Arc<Station>) {
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {},
        _ = term => {},
    }
    tracing::info!("stopping: the going run pauses at its next safe point");
    begin_stop(&st);
}

/// The worker takes nothing new, the going run pauses at its next safe point, the event
/// streams end.
fn begin_stop(st: &Station) {
    if st.stopping.swap(true, Ordering::SeqCst) {
        return;
    }
    if let Some((_, link)) = st.control.lock().ok().and_then(|c| c.clone()) {
        link.request(Request::Pause);
    }
    st.wake.notify_all();
    let _ = st.shutdown.send(true);
}

/// Waits for the worker (the going run's pause; resumed at the next start).
fn stop(worker: std::thread::JoinHandle<()>) {
    let deadline = std::time::Instant::now() + STOP_WAIT;
    while !worker.is_finished() && std::time::Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    if worker.is_finished() {
        let _ = worker.join();
    } else {
        tracing::warn!("the run did not reach a safe point in {STOP_WAIT:?}: the next start resumes it as after a crash");
    }
}
