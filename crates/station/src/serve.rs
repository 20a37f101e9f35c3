//! The long-lived process: binds (loopback, or anything with TLS), starts the worker (which
//! first resumes the run a crash or power cut interrupted), serves the API until SIGTERM or
//! Ctrl-C, then pauses the going run at its next safe point so the next start resumes it.

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

/// Runs the station until it is told to stop. `on_listening` hears the bound address (with
/// port 0 in the file, the one the system picked) before the first request is taken.
pub fn serve(
    config: Config,
    runner: Arc<dyn Runner>,
    on_listening: impl FnOnce(SocketAddr, &Config),
) -> Result<(), StationError> {
    config.check_bind()?;
    let st = Station::open(config, runner)?;
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
    let served = rt.block_on(listen(st.clone(), on_listening));
    stop(&st, worker);
    served
}

async fn listen(
    st: Arc<Station>,
    on_listening: impl FnOnce(SocketAddr, &Config),
) -> Result<(), StationError> {
    let app = crate::api::router(st.clone()).into_make_service_with_connect_info::<SocketAddr>();
    let addr = st.config.listen;
    match st.config.tls.clone() {
        None => {
            let listener = tokio::net::TcpListener::bind(addr)
                .await
                .map_err(|e| StationError::Serve(format!("cannot listen on {addr}: {e}")))?;
            let bound = listener.local_addr().unwrap_or(addr);
            on_listening(bound, &st.config);
            axum::serve(listener, app)
                .with_graceful_shutdown(shutdown_signal())
                .await
                .map_err(|e| StationError::Serve(e.to_string()))
        }
        Some(tls) => {
            let _ = rustls::crypto::aws_lc_rs::default_provider().install_default();
            let rustls = axum_server::tls_rustls::RustlsConfig::from_pem_file(&tls.cert, &tls.key)
                .await
                .map_err(|e| {
                    StationError::Serve(format!(
                        "[tls] cert {} / key {}: {e}",
                        tls.cert.display(),
                        tls.key.display()
                    ))
                })?;
            let listener = std::net::TcpListener::bind(addr)
                .map_err(|e| StationError::Serve(format!("cannot listen on {addr}: {e}")))?;
            let bound = listener.local_addr().unwrap_or(addr);
            on_listening(bound, &st.config);
            let handle = axum_server::Handle::new();
            let h = handle.clone();
            tokio::spawn(async move {
                shutdown_signal().await;
                h.graceful_shutdown(Some(Duration::from_secs(5)));
            });
            axum_server::from_tcp_rustls(listener, rustls)
                .handle(handle)
                .serve(app)
                .await
                .map_err(|e| StationError::Serve(e.to_string()))
        }
    }
}

async fn shutdown_signal() {
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
}

/// Stops the worker: the going run pauses at its next safe point (resumed at the next start).
fn stop(st: &Arc<Station>, worker: std::thread::JoinHandle<()>) {
    st.stopping.store(true, Ordering::SeqCst);
    if let Some(link) = st.control.lock().ok().and_then(|c| c.clone()) {
        link.request(Request::Pause);
    }
    st.wake.notify_all();
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
