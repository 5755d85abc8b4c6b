//! The farm's web dashboard, served by the coordinator itself (`--http ADDR`) from the same
//! state the API reads: the jobs (live), a job's page with its preview, the guide at a
//! pixel, status, iterations, log, settings, downloads, priority and cancel, and the
//! workers (the departed ones marked lost or left). Server-rendered HTML ([`pages`]), a
//! little plain JavaScript and CSS compiled into the binary ([`assets`]): nothing comes
//! from elsewhere.
//!
//! Security: behind the API token ([`auth`]: a sign-in form buys an `HttpOnly`,
//! `SameSite=Strict` session cookie; a viewer token buys one that may only look); every
//! action is a POST carrying the session's anti-forgery token and refused from another site
//! (`Sec-Fetch-Site`, `Origin`); every response is `no-store` with a strict content security
//! policy; with the coordinator's TLS, TLS only ([`tls`]). Reads use the views the API reads
//! (never the state lock); an action takes the lock on a blocking thread.

// A handler's refusal is its response, returned early: its size on the error path of an
// HTTP request costs nothing worth boxing.
#![allow(clippy::result_large_err)]

mod assets;
mod auth;
mod iterations;
mod pages;
mod throughput;
mod tls;

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Form, Router};
use maud::Markup;
use pathfarm_proto::v1;
use tokio::net::TcpListener;
use tokio::sync::Semaphore;

use super::{parse_job, resources, unix_ms, Shared};
use auth::{Role, Session, Sessions};

/// Live-update streams open at once (each is one task polling the views); more are refused
/// with 503 until one closes.
const MAX_STREAMS: usize = 64;

/// How often a live-update stream looks for changes.
const POLL: Duration = Duration::from_millis(500);

struct Dash {
    shared: Arc<Shared>,
    sessions: Sessions,
    streams: Arc<Semaphore>,
}

type Dashboard = State<Arc<Dash>>;

/// Serves the dashboard on `listener` until the task is aborted. The coordinator has a
/// token (checked when it starts).
pub(crate) async fn serve(shared: Arc<Shared>, listener: TcpListener) {
    let token = shared.cfg.token.clone().unwrap_or_default();
    let sessions = Sessions::new(&token, shared.cfg.viewer_token.as_deref());
    let dash = Arc::new(Dash {
        shared,
        sessions,
        streams: Arc::new(Semaphore::new(MAX_STREAMS)),
    });
    match dash.shared.cfg.tls.as_ref().map(tls::acceptor) {
        None => {
            if let Err(e) = axum::serve(listener, router(dash)).await {
                tracing::error!("dashboard server: {e}");
            }
        }
        Some(Ok(acceptor)) => tls::serve(listener, acceptor, router(dash)).await,
        Some(Err(e)) => tracing::error!("dashboard server: TLS: {e}"),
    }
}

fn router(dash: Arc<Dash>) -> Router {
    Router::new()
        .route("/login", get(login_form).post(login))
        .route("/logout", post(logout))
        .route("/", get(jobs_page))
        .route("/workers", get(workers_page))
        .route("/jobs/{id}", get(job_page))
        .route("/jobs/{id}/cancel", post(cancel))
        .route("/jobs/{id}/priority", post(set_priority))
        .route("/jobs/{id}/guide.png", get(guide))
        .route("/jobs/{id}/{file}", get(download))
        .route("/events", get(events))
        .route("/assets/{file}", get(asset))
        .route("/favicon.ico", get(|| asset(Path("icon.svg".to_string()))))
        .fallback(|| async { plain(StatusCode::NOT_FOUND, "not found") })
        .with_state(dash)
}

/// Headers every response carries: nothing cached, nothing framed or loaded from elsewhere.
fn guarded(mut r: Response) -> Response {
    let h = r.headers_mut();
    let set = |h: &mut HeaderMap, k: header::HeaderName, v: &'static str| {
        h.insert(k, HeaderValue::from_static(v));
    };
    set(h, header::CACHE_CONTROL, "no-store");
    set(h, header::X_CONTENT_TYPE_OPTIONS, "nosniff");
    set(h, header::X_FRAME_OPTIONS, "DENY");
    // `same-origin`, not `no-referrer`: with no referrer a browser sends `Origin: null` on a
    // form POST, and the origin check below could not tell a page of ours from a sandbox.
    set(h, header::REFERRER_POLICY, "same-origin");
    set(
        h,
        header::CONTENT_SECURITY_POLICY,
        "default-src 'self'; img-src 'self' blob:; style-src 'self'; script-src 'self'; \
         connect-src 'self'; form-action 'self'; frame-ancestors 'none'; base-uri 'none'",
    );
    r
}

fn html(status: StatusCode, m: Markup) -> Response {
    let ct = [(header::CONTENT_TYPE, "text/html; charset=utf-8")];
    guarded((status, ct, m.into_string()).into_response())
}

fn plain(status: StatusCode, text: impl Into<String>) -> Response {
    let ct = [(header::CONTENT_TYPE, "text/plain; charset=utf-8")];
    guarded((status, ct, text.into()).into_response())
}

fn see_other(to: &str) -> Response {
    let loc = HeaderValue::from_str(to).unwrap_or(HeaderValue::from_static("/"));
    guarded((StatusCode::SEE_OTHER, [(header::LOCATION, loc)]).into_response())
}

/// The request's session, or the response for a request without one: the sign-in page
/// for a page, 401 for anything else.
fn session(d: &Dash, headers: &HeaderMap, page: bool) -> Result<Session, Response> {
    let cookie = headers.get(header::COOKIE).and_then(|v| v.to_str().ok());
    match d.sessions.session(cookie, Instant::now()) {
        Some(s) => Ok(s),
        None if page => Err(see_other("/login")),
        None => Err(plain(StatusCode::UNAUTHORIZED, "sign in first")),
    }
}

async fn login_form() -> Response {
    html(StatusCode::OK, pages::login(None))
}

#[derive(serde::Deserialize)]
struct LoginForm {
    token: String,
}

async fn login(State(d): Dashboard, form: Form<LoginForm>) -> Response {
    let token = &form.token;
    let id = (token.len() <= 4096)
        .then(|| d.sessions.sign_in(token, Instant::now()))
        .flatten();
    let Some(id) = id else {
        return html(
            StatusCode::UNAUTHORIZED,
            pages::login(Some("That is not the coordinator's token.")),
        );
    };
    let cookie = format!(
        "{}={id}; HttpOnly; SameSite=Strict; Path=/; Max-Age={}",
        auth::COOKIE,
        auth::LIFETIME.as_secs()
    );
    with_cookie(&d, see_other("/"), &cookie)
}

async fn logout(State(d): Dashboard, headers: HeaderMap) -> Response {
    if let Err(r) = same_site(&headers) {
        return r;
    }
    let cookie = headers.get(header::COOKIE).and_then(|v| v.to_str().ok());
    d.sessions.sign_out(cookie);
    let gone = format!(
        "{}=; HttpOnly; SameSite=Strict; Path=/; Max-Age=0",
        auth::COOKIE
    );
    with_cookie(&d, see_other("/login"), &gone)
}

/// `r` setting the cookie `value` (a `Set-Cookie` header's value), `Secure` when the
/// dashboard is served over TLS (the browser then never sends it in clear).
fn with_cookie(d: &Dash, mut r: Response, value: &str) -> Response {
    let secure = match d.shared.cfg.tls {
        Some(_) => "; Secure",
        None => "",
    };
    if let Ok(v) = HeaderValue::from_str(&format!("{value}{secure}")) {
        r.headers_mut().insert(header::SET_COOKIE, v);
    }
    r
}

#[derive(serde::Deserialize, Default)]
struct Filter {
    state: Option<String>,
    job: Option<String>,
    /// `workers`: the workers page's live content instead of jobs.
    view: Option<String>,
}

/// What a live stream sends.
#[derive(Clone, Copy)]
enum Live {
    Jobs(Option<v1::JobState>),
    Job(u64),
    Workers,
}

/// What `/events` streams for the query `q`: a job's page (`?job=`), the workers page
/// (`?view=workers`) or the jobs table (`?state=`, optional); `Err` for anything else.
fn live_of(d: &Dash, q: &Filter) -> Result<Live, Response> {
    match (q.job.as_deref(), q.view.as_deref()) {
        (Some(id), None) => job_number(d, id).map(Live::Job),
        (None, Some("workers")) => Ok(Live::Workers),
        (None, None) => state_filter(q).map(Live::Jobs),
        (Some(_), Some(_)) => Err(plain(
            StatusCode::BAD_REQUEST,
            "job and view: one or the other",
        )),
        (None, Some(v)) => {
            let echo = resources::echo(v);
            Err(plain(
                StatusCode::BAD_REQUEST,
                format!("view: no view {echo}"),
            ))
        }
    }
}

/// `?state=NAME` as a state: `Err` for a name that is none of them.
fn state_filter(q: &Filter) -> Result<Option<v1::JobState>, Response> {
    let Some(name) = q.state.as_deref() else {
        return Ok(None);
    };
    (pages::STATES.into_iter())
        .find(|s| pages::state_name(*s) == name)
        .map(Some)
        .ok_or_else(|| {
            let echo = resources::echo(name);
            plain(StatusCode::BAD_REQUEST, format!("state: no state {echo}"))
        })
}

/// Every job (in `filter`'s state), newest first.
fn job_list(d: &Dash, filter: Option<v1::JobState>) -> Vec<v1::JobStatus> {
    let views = d.shared.views.read().unwrap_or_else(|e| e.into_inner());
    let mut jobs: Vec<v1::JobStatus> = (views.values().rev())
        .map(|v| v.status.borrow().clone())
        .filter(|s| filter.is_none_or(|f| s.state == f as i32))
        .collect();
    jobs.truncate(1000);
    jobs
}

async fn jobs_page(State(d): Dashboard, headers: HeaderMap, q: Query<Filter>) -> Response {
    if let Err(r) = session(&d, &headers, true) {
        return r;
    }
    match state_filter(&q) {
        Ok(filter) => html(StatusCode::OK, pages::jobs(&job_list(&d, filter), filter)),
        Err(r) => r,
    }
}

async fn workers_page(State(d): Dashboard, headers: HeaderMap) -> Response {
    if let Err(r) = session(&d, &headers, true) {
        return r;
    }
    html(StatusCode::OK, pages::workers(workers_now(&d)))
}

/// The workers page's content as it stands: the throughput chart and the workers table.
fn workers_now(d: &Dash) -> maud::Markup {
    let workers = (d.shared.workers_view.read())
        .unwrap_or_else(|e| e.into_inner())
        .clone();
    let series = (d.shared.throughput.lock())
        .unwrap_or_else(|e| e.into_inner())
        .series(d.shared.now());
    pages::workers_body(&workers, unix_ms(), &throughput::chart(&series))
}

/// The job `id` names, or 404.
fn job_number(d: &Dash, id: &str) -> Result<u64, Response> {
    let n = parse_job(id).filter(|&n| d.shared.view(n).is_some());
    n.ok_or_else(|| {
        plain(
            StatusCode::NOT_FOUND,
            format!("no job {}", resources::echo(id)),
        )
    })
}

async fn job_page(State(d): Dashboard, headers: HeaderMap, Path(id): Path<String>) -> Response {
    let s = match session(&d, &headers, true) {
        Ok(s) => s,
        Err(r) => return r,
    };
    let view = match job_number(&d, &id) {
        Ok(n) => d.shared.view(n).expect("checked"),
        Err(r) => return r,
    };
    let status = view.status.borrow().clone();
    let log = d.shared.cfg.job_logs.lines(&status.job_id);
    let page = pages::JobPage {
        status: &status,
        settings: view.settings.as_ref(),
        root: &view.root,
        image: view.image,
        csrf: &s.csrf,
        log: &log,
        can_act: s.role == Role::Operator,
    };
    html(StatusCode::OK, pages::job(&page))
}

/// The job `id` names, for a request with a session (else 401, or 404 for no such job).
fn signed_in_job(d: &Dash, headers: &HeaderMap, id: &str) -> Result<u64, Response> {
    session(d, headers, false)?;
    job_number(d, id)
}

/// Refuses a request another site made the browser send: `Sec-Fetch-Site` other than
/// same-origin (or none), or an `Origin` that is not the `Host` it was sent to.
fn same_site(headers: &HeaderMap) -> Result<(), Response> {
    let get = |k: header::HeaderName| headers.get(k).and_then(|v| v.to_str().ok());
    let fetch_site = headers.get("sec-fetch-site").and_then(|v| v.to_str().ok());
    let cross = |why: &str| plain(StatusCode::FORBIDDEN, format!("refused: {why}"));
    if fetch_site.is_some_and(|s| s != "same-origin" && s != "none") {
        return Err(cross("a request from another site"));
    }
    if let Some(origin) = get(header::ORIGIN) {
        let host = get(header::HOST).unwrap_or("");
        let bare = origin.split_once("://").map_or(origin, |(_, h)| h);
        if origin == "null" || bare != host {
            return Err(cross("a request from another origin"));
        }
    }
    Ok(())
}

#[derive(serde::Deserialize)]
struct ActionForm {
    csrf: String,
}

#[derive(serde::Deserialize)]
struct PriorityForm {
    csrf: String,
    priority: String,
}

/// The job an action's POST names, once the request passed an action's checks: a session,
/// from this site, with the session's anti-forgery token.
fn action_job(d: &Dash, headers: &HeaderMap, id: &str, csrf: &str) -> Result<u64, Response> {
    let s = session(d, headers, false)?;
    same_site(headers)?;
    if s.role != Role::Operator {
        return Err(plain(
            StatusCode::FORBIDDEN,
            "refused: this session may look, not act (signed in with the viewer token)",
        ));
    }
    if csrf != s.csrf {
        return Err(plain(
            StatusCode::FORBIDDEN,
            "refused: the form's token is not this session's",
        ));
    }
    job_number(d, id)
}

async fn cancel(
    State(d): Dashboard,
    headers: HeaderMap,
    Path(id): Path<String>,
    form: Form<ActionForm>,
) -> Response {
    let n = match action_job(&d, &headers, &id, &form.csrf) {
        Ok(n) => n,
        Err(r) => return r,
    };
    act(&d, n, "cancel", move |shared, st| {
        let why = "cancelled from the dashboard".to_string();
        shared.end_job(st, n, v1::JobState::Cancelled, why);
    })
    .await
}

/// Does `f` to the state (under the lock, on a blocking thread), then sends the browser
/// back to job `n`'s page.
async fn act(
    d: &Dash,
    n: u64,
    what: &str,
    f: impl FnOnce(&Arc<Shared>, &mut super::State) + Send + 'static,
) -> Response {
    let shared = d.shared.clone();
    let done = tokio::task::spawn_blocking(move || f(&shared, &mut shared.lock())).await;
    match done {
        Ok(()) => see_other(&format!("/jobs/{}", super::job_name(n))),
        Err(e) => plain(StatusCode::INTERNAL_SERVER_ERROR, format!("{what}: {e}")),
    }
}

async fn set_priority(
    State(d): Dashboard,
    headers: HeaderMap,
    Path(id): Path<String>,
    form: Form<PriorityForm>,
) -> Response {
    let n = match action_job(&d, &headers, &id, &form.csrf) {
        Ok(n) => n,
        Err(r) => return r,
    };
    let Ok(priority) = form.priority.trim().parse::<i32>() else {
        let echo = super::resources::echo(&form.priority);
        return plain(
            StatusCode::BAD_REQUEST,
            format!("priority: {echo} is not a whole number (a 32-bit integer)"),
        );
    };
    act(&d, n, "priority", move |shared, st| {
        shared.set_priority(st, n, priority);
    })
    .await
}

#[derive(serde::Deserialize)]
struct PixelQuery {
    x: u32,
    y: u32,
}

/// `/jobs/ID/guide.png?x=X&y=Y`: the directions the job's latest tree learned at the first
/// hit of pixel (X, Y) (`guide_view`).
async fn guide(
    State(d): Dashboard,
    headers: HeaderMap,
    Path(id): Path<String>,
    q: Query<PixelQuery>,
) -> Response {
    let n = match signed_in_job(&d, &headers, &id) {
        Ok(n) => n,
        Err(r) => return r,
    };
    let shared = d.shared.clone();
    let (x, y) = (q.x, q.y);
    let drawn = tokio::task::spawn_blocking(move || shared.guide_picture(n, x, y)).await;
    match drawn {
        Ok(Ok(png)) => guarded(([(header::CONTENT_TYPE, "image/png")], png).into_response()),
        Ok(Err(e)) => plain(StatusCode::NOT_FOUND, e.to_string()),
        Err(e) => plain(StatusCode::INTERNAL_SERVER_ERROR, format!("guide: {e}")),
    }
}

/// `/jobs/ID/FILE`: `preview.png` (the image so far, or the final PNG), and once the job is
/// done `result.exr`, `result.png` and `tree.sdt`.
async fn download(
    State(d): Dashboard,
    headers: HeaderMap,
    Path((id, file)): Path<(String, String)>,
) -> Response {
    let n = match signed_in_job(&d, &headers, &id) {
        Ok(n) => n,
        Err(r) => return r,
    };
    let (kind, content_type) = match file.as_str() {
        "preview.png" => (v1::ResultKind::PngPreview, "image/png"),
        "result.png" => (v1::ResultKind::PngPreview, "image/png"),
        "result.exr" => (v1::ResultKind::Exr, "image/x-exr"),
        "tree.sdt" => (v1::ResultKind::SdTree, "application/octet-stream"),
        other => {
            let echo = resources::echo(other);
            return plain(StatusCode::NOT_FOUND, format!("no file {echo}"));
        }
    };
    let shared = d.shared.clone();
    let found = tokio::task::spawn_blocking(move || shared.result_blob(n, kind)).await;
    let Ok(Ok(digest)) = found else {
        return plain(StatusCode::NOT_FOUND, format!("{file}: not there yet"));
    };
    let path = d.shared.blobs.path(&digest);
    let mut r = file_response(path, content_type);
    if file != "preview.png" {
        let name = format!("attachment; filename=\"{}-{file}\"", super::job_name(n));
        if let Ok(v) = HeaderValue::from_str(&name) {
            r.headers_mut().insert(header::CONTENT_DISPOSITION, v);
        }
    }
    r
}

/// A file streamed in parts of 1 MiB, read on a blocking thread.
fn file_response(path: std::path::PathBuf, content_type: &'static str) -> Response {
    use std::io::Read;
    let (tx, rx) = tokio::sync::mpsc::channel::<std::io::Result<Vec<u8>>>(2);
    tokio::task::spawn_blocking(move || {
        let mut f = match std::fs::File::open(&path) {
            Ok(f) => f,
            Err(e) => return drop(tx.blocking_send(Err(e))),
        };
        loop {
            let mut buf = vec![0u8; 1 << 20];
            match f.read(&mut buf) {
                Ok(0) => return,
                Ok(k) => {
                    buf.truncate(k);
                    if tx.blocking_send(Ok(buf)).is_err() {
                        return;
                    }
                }
                Err(e) => return drop(tx.blocking_send(Err(e))),
            }
        }
    });
    let body = axum::body::Body::from_stream(tokio_stream::wrappers::ReceiverStream::new(rx));
    guarded(([(header::CONTENT_TYPE, content_type)], body).into_response())
}

/// Live updates (server-sent events): `?job=ID` sends that job's status block (`job`
/// events) whenever it changes; otherwise the jobs table's rows (`jobs` events, `?state=`
/// as on the page).
async fn events(State(d): Dashboard, headers: HeaderMap, q: Query<Filter>) -> Response {
    if let Err(r) = session(&d, &headers, false) {
        return r;
    }
    let live = match live_of(&d, &q) {
        Ok(l) => l,
        Err(r) => return r,
    };
    let Ok(permit) = d.streams.clone().try_acquire_owned() else {
        return plain(StatusCode::SERVICE_UNAVAILABLE, "too many live pages open");
    };
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Event, std::convert::Infallible>>(4);
    let dash = d.clone();
    tokio::spawn(async move {
        let _permit = permit;
        let mut last = String::new();
        let mut parts_sent = [String::new(), String::new()];
        loop {
            let (name, now, parts) = match live {
                Live::Job(n) => match dash.shared.view(n) {
                    Some(v) => {
                        let s = v.status.borrow();
                        let log = dash.shared.cfg.job_logs.lines(&s.job_id);
                        let parts = [
                            iterations::iterations(&s).into_string(),
                            pages::job_log(&log).into_string(),
                        ];
                        ("job", pages::job_status(&s).into_string(), Some(parts))
                    }
                    None => return,
                },
                Live::Jobs(filter) => (
                    "jobs",
                    pages::job_rows(&job_list(&dash, filter)).into_string(),
                    None,
                ),
                Live::Workers => ("workers", workers_now(&dash).into_string(), None),
            };
            if now != last {
                if tx
                    .send(Ok(Event::default().event(name).data(&now)))
                    .await
                    .is_err()
                {
                    return;
                }
                last = now;
            }
            // A job page's other live sections, each sent when it changed.
            for (k, part) in parts.into_iter().flatten().enumerate() {
                if part == parts_sent[k] {
                    continue;
                }
                let event = Event::default().event(["iterations", "log"][k]).data(&part);
                if tx.send(Ok(event)).await.is_err() {
                    return;
                }
                parts_sent[k] = part;
            }
            tokio::select! {
                _ = tokio::time::sleep(POLL) => {}
                _ = tx.closed() => return,
            }
        }
    });
    let stream = tokio_stream::wrappers::ReceiverStream::new(rx);
    guarded(
        Sse::new(stream)
            .keep_alive(KeepAlive::default())
            .into_response(),
    )
}

async fn asset(Path(file): Path<String>) -> Response {
    match assets::get(&file) {
        Some((body, content_type)) => {
            guarded(([(header::CONTENT_TYPE, content_type)], body).into_response())
        }
        None => plain(
            StatusCode::NOT_FOUND,
            format!("no asset {}", resources::echo(&file)),
        ),
    }
}
