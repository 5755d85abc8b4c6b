//! The dashboard's HTML, rendered on the server (maud escapes every value it inserts): the
//! sign-in form, the jobs table, a job's page and the workers table. The table rows are
//! their own functions: the live updates send them again.

use maud::{html, Markup, DOCTYPE};
use pathfarm_proto::v1;

/// A page: the header with its navigation, `body`, the stylesheet and the script.
pub(super) fn layout(title: &str, signed_in: bool, body: Markup) -> Markup {
    html! {
        (DOCTYPE)
        html lang="en" {
            head {
                meta charset="utf-8";
                meta name="viewport" content="width=device-width, initial-scale=1";
                title { (title) " · pathfarm" }
                link rel="stylesheet" href="/assets/app.css";
                link rel="icon" href="/assets/icon.svg" type="image/svg+xml";
                script src="/assets/app.js" defer {}
            }
            body {
                header {
                    a.brand href="/" { "pathfarm" }
                    @if signed_in {
                        nav {
                            a href="/" { "Jobs" }
                            a href="/workers" { "Workers" }
                            form method="post" action="/logout" { button { "Sign out" } }
                        }
                    }
                }
                main { (body) }
            }
        }
    }
}

/// The sign-in form (`error`: why the last attempt failed).
pub(super) fn login(error: Option<&str>) -> Markup {
    layout(
        "Sign in",
        false,
        html! {
            form.card.login method="post" action="/login" {
                h1 { "Sign in" }
                p { "The coordinator's API token (" code { "PATHFARM_TOKEN" } ")." }
                @if let Some(e) = error { p.error { (e) } }
                input type="password" name="token" autocomplete="current-password" autofocus;
                button { "Sign in" }
            }
        },
    )
}

/// Every job, newest first (`filter`: only those in that state).
pub(super) fn jobs(jobs: &[v1::JobStatus], filter: Option<v1::JobState>) -> Markup {
    let chosen = |s: Option<v1::JobState>| if s == filter { "chosen" } else { "" };
    layout(
        "Jobs",
        true,
        html! {
            h1 { "Jobs" }
            nav.filters {
                a class=(chosen(None)) href="/" { "all" }
                @for s in STATES {
                    a class=(chosen(Some(s))) href={ "/?state=" (state_name(s)) } { (state_name(s)) }
                }
            }
            table #jobs data-live={ "/events" (filter.map_or(String::new(), |s| format!("?state={}", state_name(s)))) } {
                thead { tr {
                    th { "job" } th { "state" } th { "iteration" } th { "unit" } th { "spp" }
                    th { "ETA" } th { "priority" } th { "non-finite" } th { "why it failed" }
                } }
                tbody { (job_rows(jobs)) }
            }
        },
    )
}

/// The jobs table's rows.
pub(super) fn job_rows(jobs: &[v1::JobStatus]) -> Markup {
    html! {
        @for j in jobs {
            tr {
                td { a href={ "/jobs/" (j.job_id) } { (j.job_id) } @if !j.name.is_empty() { " " span.muted { (j.name) } } }
                td { (badge(state_of(j))) }
                td.num { (j.iteration) }
                td.num { (j.tiles_done) " / " (j.tiles_total) " tiles" }
                td.num { (j.spp_done) }
                td.num { (eta(j.eta_seconds)) }
                td.num { (j.priority) }
                td.num { (j.nonfinite) }
                td.reason { (j.failure_reason) }
            }
        }
        @if jobs.is_empty() { tr { td colspan="9" .muted { "No jobs." } } }
    }
}

/// What a job's page shows: its status and what its submission fixed.
pub(super) struct JobPage<'a> {
    pub(super) status: &'a v1::JobStatus,
    pub(super) settings: Option<&'a v1::JobSettings>,
    pub(super) root: &'a str,
    pub(super) image: Option<v1::Resolution>,
    pub(super) csrf: &'a str,
    /// The job's last log lines, oldest first.
    pub(super) log: &'a [String],
    /// Whether the session may act (an operator's) or only look (a viewer's).
    pub(super) can_act: bool,
}

/// A job's page: its preview (with an exposure control), status, settings and actions.
pub(super) fn job(p: &JobPage<'_>) -> Markup {
    let j = p.status;
    let done = state_of(j) == v1::JobState::Done;
    layout(
        &j.job_id,
        true,
        html! {
            h1 { (j.job_id) @if !j.name.is_empty() { " " span.muted { (j.name) } } }
            div.job {
                figure.preview {
                    @if j.preview_available {
                        img #preview src={ "/jobs/" (j.job_id) "/preview.png" } alt="the image so far";
                        label { "exposure " input #exposure type="range" min="-4" max="4" step="0.5" value="0"; output #ev { "0" } }
                    } @else {
                        p.muted { "The preview appears once the first iteration is done." }
                    }
                    figcaption { "Click the image: what the guide learned at that pixel's first hit." }
                }
                section.card #status data-live={ "/events?job=" (j.job_id) } { (job_status(j)) }
                section.card.guide.wide {
                    h2 { "The guide at a pixel" }
                    p #guide-caption .muted { "Click a pixel of the preview." }
                    img #guide hidden alt="the learned distribution of incident light" data-job=(j.job_id);
                    div.panel-names #guide-names hidden { span { "BSDF sampling" } span { "guided mixture" } span { "learned distribution" } }
                    p.muted { "Each panel is the sphere of directions (across: cos theta of the world z axis, down: phi) at the pixel's first hit: where sampling the surface alone sends paths, where the guided mixture sends them, and the incident light the guide learned, brighter where more." }
                }
                section.card.wide #iterations { (super::iterations::iterations(j)) }
                section.card.wide #log { (job_log(p.log)) }
                section.card {
                    h2 { "Scene" }
                    (settings(p))
                }
                section.card {
                    h2 { "Actions" }
                    @if done {
                        p {
                            a.button href={ "/jobs/" (j.job_id) "/result.exr" } download { "EXR" } " "
                            a.button href={ "/jobs/" (j.job_id) "/result.png" } download { "PNG" } " "
                            a.button href={ "/jobs/" (j.job_id) "/tree.sdt" } download { "SD-tree" }
                        }
                    }
                    @if !p.can_act {
                        p.muted { "Signed in as a viewer: you can look, not act." }
                    }
                    @if p.can_act && !is_terminal(state_of(j)) {
                        form.priority method="post" action={ "/jobs/" (j.job_id) "/priority" } {
                            input type="hidden" name="csrf" value=(p.csrf);
                            label { "priority "
                                input #priority type="number" name="priority" step="1" value=(j.priority);
                            }
                            " " button { "Set" }
                        }
                        form method="post" action={ "/jobs/" (j.job_id) "/cancel" } {
                            input type="hidden" name="csrf" value=(p.csrf);
                            button.danger { "Cancel the job" }
                        }
                    }
                }
            }
        },
    )
}

/// A job's last log lines (sent again by the live updates), newest at the bottom.
pub(super) fn job_log(lines: &[String]) -> Markup {
    html! {
        h2 { "Log" span.muted { " (the last " (lines.len()) " lines of the coordinator's log for this job)" } }
        @if lines.is_empty() {
            p.muted { "Nothing logged for this job yet." }
        } @else {
            pre.log { @for l in lines { (l) "\n" } }
        }
    }
}

/// A job's status block (sent again by the live updates).
pub(super) fn job_status(j: &v1::JobStatus) -> Markup {
    // What the page's script compares to reload the preview: it changes at iteration ends
    // and at the end of the job, when the coordinator makes a new one.
    let version = format!("{}-{}", j.iteration, j.state);
    html! {
        h2 { "Status" }
        span hidden data-version=(version) data-preview=(j.preview_available) {}
        dl {
            dt { "state" } dd { (badge(state_of(j))) }
            dt { "iteration" } dd { (j.iteration) ", unit " (j.unit) ": " (j.tiles_done) " / " (j.tiles_total) " tiles" }
            dt { "samples per pixel" } dd { (j.spp_done) }
            dt { "ETA" } dd { (eta(j.eta_seconds)) }
            dt { "priority" } dd { (j.priority) }
            dt { "non-finite samples" } dd { (j.nonfinite) }
            @if !j.batch.is_empty() { dt { "batch" } dd { (j.batch) } }
            @if !j.failure_reason.is_empty() { dt { "why it ended" } dd.reason { (j.failure_reason) } }
            @if !j.blocked_workers.is_empty() {
                dt { "workers blocked" } dd { @for b in &j.blocked_workers { div { (b) } } }
            }
        }
    }
}

fn settings(p: &JobPage<'_>) -> Markup {
    html! {
        dl {
            dt { "scene file" } dd { code { (p.root) } }
            @if let Some(r) = p.image { dt { "resolution" } dd { (r.width) " x " (r.height) } }
            @if let Some(s) = p.settings {
                @match s.budget {
                    Some(v1::job_settings::Budget::Spp(spp)) => { dt { "spp budget" } dd { (spp) } }
                    Some(v1::job_settings::Budget::TimeSeconds(t)) => { dt { "time budget" } dd { (t) " s" } }
                    None => { dt { "budget" } dd { "the scene's sample count" } }
                }
                @if let Some(sc) = &s.scene {
                    @if let Some(seed) = sc.seed { dt { "seed" } dd { (seed) } }
                    @if let Some(i) = &sc.integrator { dt { "integrator" } dd { (i) } }
                    @if !sc.defines.is_empty() {
                        dt { "-D" } dd { @for d in &sc.defines { div { code { (d.name) "=" (d.value) } } } }
                    }
                }
            }
        }
    }
}

/// The workers page: its content ([`workers_body`]) kept current by the live updates.
pub(super) fn workers(body: Markup) -> Markup {
    layout(
        "Workers",
        true,
        html! {
            h1 { "Workers" }
            div #workers data-live="/events?view=workers" { (body) }
        },
    )
}

/// The farm's throughput and the workers table.
pub(super) fn workers_body(
    workers: &[v1::WorkerInfo],
    now_unix_ms: u64,
    throughput: &Markup,
) -> Markup {
    html! {
        (throughput)
        table {
            thead { tr {
                th { "worker" } th { "host" } th { "threads" } th { "state" } th { "tiles done" }
                th { "leases" } th { "last heartbeat" } th { "build" }
            } }
            tbody {
                @for w in workers {
                    tr {
                        td { (w.worker_id) @if !w.worker_name.is_empty() { " " span.muted { (w.worker_name) } } }
                        td { (w.host_name) }
                        td.num { (w.threads) }
                        td {
                            span class={ "state " (worker_class(w)) } { (worker_state(w)) }
                            @if !w.connected {
                                " " span.muted title=(w.departed_reason) {
                                    (ago(now_unix_ms, w.departed_unix_ms))
                                }
                            }
                        }
                        td.num { (w.tiles_done) }
                        td.num { (w.lease_ids.len()) }
                        td.num { (ago(now_unix_ms, w.last_heartbeat_unix_ms)) }
                        td { code { (w.build_id) } }
                    }
                }
                @if workers.is_empty() { tr { td colspan="8" .muted { "No workers." } } }
            }
        }
    }
}

/// A worker state's badge colour.
fn worker_class(w: &v1::WorkerInfo) -> &'static str {
    match worker_state(w) {
        "lost" => "bad",
        "left" => "off",
        "rendering" => "busy",
        _ => "ok",
    }
}

/// The states the jobs table can be filtered by.
pub(super) use super::super::metrics::STATES;

pub(super) fn state_of(j: &v1::JobStatus) -> v1::JobState {
    v1::JobState::try_from(j.state).unwrap_or(v1::JobState::Unspecified)
}

/// A state's name in the page and in `?state=`.
pub(super) fn state_name(s: v1::JobState) -> &'static str {
    match s {
        v1::JobState::Queued => "queued",
        v1::JobState::Training => "training",
        v1::JobState::FinalPass => "final-pass",
        v1::JobState::Assembling => "assembling",
        v1::JobState::Done => "done",
        v1::JobState::Failed => "failed",
        v1::JobState::Cancelled => "cancelled",
        v1::JobState::Unspecified => "unknown",
    }
}

/// A state as a coloured badge.
fn badge(s: v1::JobState) -> Markup {
    let class = match s {
        v1::JobState::Done => "ok",
        v1::JobState::Failed => "bad",
        v1::JobState::Cancelled => "off",
        v1::JobState::Queued | v1::JobState::Unspecified => "wait",
        _ => "busy",
    };
    html! { span class={ "state " (class) } { (state_name(s)) } }
}

pub(super) fn is_terminal(s: v1::JobState) -> bool {
    matches!(
        s,
        v1::JobState::Done | v1::JobState::Failed | v1::JobState::Cancelled
    )
}

/// A worker's state: a departed one "left" after draining, "lost" otherwise (killed,
/// silent past the heartbeat timeout, cut off).
fn worker_state(w: &v1::WorkerInfo) -> &'static str {
    match (w.connected, w.draining, w.lease_ids.is_empty()) {
        (false, true, _) => "left",
        (false, false, _) => "lost",
        (true, true, _) => "draining",
        (true, false, false) => "rendering",
        (true, false, true) => "idle",
    }
}

fn eta(s: Option<f64>) -> String {
    match s {
        Some(s) if s.is_finite() && s >= 0.0 => format!("{:.0} s", s),
        _ => "-".into(),
    }
}

fn ago(now_ms: u64, then_ms: u64) -> String {
    match then_ms {
        0 => "-".into(),
        t => format!("{:.1} s ago", now_ms.saturating_sub(t) as f64 / 1000.0),
    }
}
