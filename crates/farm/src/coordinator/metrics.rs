//! `GET /metrics` in the Prometheus text format, served by a minimal HTTP/1.1 responder on
//! `CoordinatorConfig::metrics` (no HTTP framework: one request per connection).

use std::fmt::Write as _;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;

use super::{Shared, State};
use pathfarm_proto::v1;

/// Renders the current metrics.
pub(crate) fn render(shared: &Shared) -> String {
    let mut out = String::new();
    let st: std::sync::MutexGuard<'_, State> = shared.lock();
    let _ = writeln!(
        out,
        "# HELP pathfarm_jobs Jobs by state.\n# TYPE pathfarm_jobs gauge"
    );
    for state in [
        v1::JobState::Queued,
        v1::JobState::Training,
        v1::JobState::FinalPass,
        v1::JobState::Assembling,
        v1::JobState::Done,
        v1::JobState::Failed,
        v1::JobState::Cancelled,
    ] {
        let count = st
            .jobs
            .iter()
            .filter(|(&n, j)| {
                super::status_of(n, &j.record, j.active.as_ref()).state == state as i32
            })
            .count();
        let _ = writeln!(
            out,
            "pathfarm_jobs{{state=\"{}\"}} {count}",
            state.as_str_name()
        );
    }
    let workers = st.workers.values().filter(|w| w.tx.is_some()).count();
    let m = &shared.metrics;
    let gauges = [
        ("pathfarm_workers", "Connected workers.", workers as u64),
        (
            "pathfarm_tiles_in_flight",
            "Live leases.",
            st.sched.in_flight_total() as u64,
        ),
        (
            "pathfarm_tiles_ready",
            "Tiles waiting for a worker.",
            st.sched.ready_total() as u64,
        ),
    ];
    drop(st);
    for (name, help, v) in gauges {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
    }
    let counters = [
        (
            "pathfarm_blob_bytes_fetched_total",
            "Bytes of blobs and results sent.",
            m.blob_bytes_fetched.load(Ordering::Relaxed),
        ),
        (
            "pathfarm_tile_bytes_uploaded_total",
            "Bytes of tile uploads received.",
            m.tile_bytes_uploaded.load(Ordering::Relaxed),
        ),
        (
            "pathfarm_tiles_accepted_total",
            "Tiles accepted.",
            m.tiles_accepted.load(Ordering::Relaxed),
        ),
        (
            "pathfarm_tiles_rejected_total",
            "Tile uploads rejected.",
            m.tiles_rejected.load(Ordering::Relaxed),
        ),
    ];
    for (name, help, v) in counters {
        let _ = writeln!(
            out,
            "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}"
        );
    }
    let secs = m.merge_nanos.load(Ordering::Relaxed) as f64 * 1e-9;
    let _ = writeln!(
        out,
        "# HELP pathfarm_merge_seconds_total Seconds spent merging tiles into sessions (and refining).\n\
         # TYPE pathfarm_merge_seconds_total counter\npathfarm_merge_seconds_total {secs}"
    );
    out
}

/// Serves `/metrics` on `listener` forever.
pub(crate) async fn serve(shared: Arc<Shared>, listener: TcpListener) {
    loop {
        let Ok((mut sock, _)) = listener.accept().await else {
            continue;
        };
        let shared = shared.clone();
        tokio::spawn(async move {
            let mut buf = vec![0u8; 4096];
            let mut got = 0;
            while got < buf.len() {
                match sock.read(&mut buf[got..]).await {
                    Ok(0) | Err(_) => break,
                    Ok(k) => got += k,
                }
                if buf[..got].windows(4).any(|w| w == b"\r\n\r\n") {
                    break;
                }
            }
            let request = String::from_utf8_lossy(&buf[..got]);
            let response = if request.starts_with("GET /metrics ") {
                let body = render(&shared);
                format!(
                    "HTTP/1.1 200 OK\r\ncontent-type: text/plain; version=0.0.4\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
                    body.len()
                )
            } else {
                "HTTP/1.1 404 Not Found\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"
                    .to_string()
            };
            let _ = sock.write_all(response.as_bytes()).await;
            let _ = sock.shutdown().await;
        });
    }
}
