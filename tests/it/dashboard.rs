//! The web dashboard (`pathfarm coordinator --http ADDR`) against a real coordinator and
//! workers on 127.0.0.1, over plain HTTP/1.1 written by hand: every route refuses a request
//! without a session, the token signs in with a cookie a script cannot read, hostile paths
//! and queries are refused, an action from another site or without the session's
//! anti-forgery token is refused, a job's page and downloads are those of the API, and a
//! job cancelled from its page is cancelled.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use super::farm::{free_port, submit, submit_ok, Farm, TOKEN};

/// An HTTP response: status, headers (names lower case), body (de-chunked).
struct Reply {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Reply {
    fn header(&self, name: &str) -> Option<&str> {
        let found = self.headers.iter().find(|(k, _)| k == name);
        found.map(|(_, v)| v.as_str())
    }

    fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

/// One request on its own connection (`Connection: close`), read to its end.
fn request(port: u16, method: &str, path: &str, headers: &[(&str, &str)], body: &str) -> Reply {
    let mut s = TcpStream::connect(("127.0.0.1", port)).expect("the dashboard listens");
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let mut req =
        format!("{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n");
    for (k, v) in headers {
        req += &format!("{k}: {v}\r\n");
    }
    if method == "POST" {
        req += "Content-Type: application/x-www-form-urlencoded\r\n";
        req += &format!("Content-Length: {}\r\n", body.len());
    }
    req += "\r\n";
    req += body;
    s.write_all(req.as_bytes()).unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).expect("the response");
    parse(&raw)
}

fn parse(raw: &[u8]) -> Reply {
    let end = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a header block");
    let head = String::from_utf8_lossy(&raw[..end]).into_owned();
    let mut lines = head.lines();
    let status = lines
        .next()
        .unwrap()
        .split(' ')
        .nth(1)
        .unwrap()
        .parse()
        .unwrap();
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    let mut body = raw[end + 4..].to_vec();
    if headers
        .iter()
        .any(|(k, v)| k == "transfer-encoding" && v.contains("chunked"))
    {
        body = dechunk(&body);
    }
    Reply {
        status,
        headers,
        body,
    }
}

fn dechunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let nl = b
            .windows(2)
            .position(|w| w == b"\r\n")
            .expect("a chunk size");
        let size =
            usize::from_str_radix(std::str::from_utf8(&b[..nl]).unwrap().trim(), 16).unwrap();
        if size == 0 {
            return out;
        }
        out.extend_from_slice(&b[nl + 2..nl + 2 + size]);
        b = &b[nl + 2 + size + 2..];
    }
}

/// Signs in: the session cookie (`name=value`).
/// The dashboard's second token: it may look, not act.
const VIEWER: &str = "viewer-secret";

fn sign_in(port: u16) -> String {
    sign_in_with(port, TOKEN)
}

fn sign_in_with(port: u16, token: &str) -> String {
    let r = request(port, "POST", "/login", &[], &format!("token={token}"));
    assert_eq!(r.status, 303, "{}", r.text());
    let cookie = r.header("set-cookie").expect("a session cookie");
    for attribute in ["HttpOnly", "SameSite=Strict", "Path=/"] {
        assert!(cookie.contains(attribute), "{attribute} missing: {cookie}");
    }
    cookie.split(';').next().unwrap().to_string()
}

/// The anti-forgery token in a page's form.
fn csrf_of(page: &str) -> String {
    let at = page
        .find("name=\"csrf\" value=\"")
        .expect("a form with the token");
    let rest = &page[at + "name=\"csrf\" value=\"".len()..];
    rest[..rest.find('"').unwrap()].to_string()
}

fn start(tag: &str, workers: usize) -> (Farm, u16) {
    let port = free_port();
    let addr = format!("127.0.0.1:{port}");
    let farm = Farm::start_args(tag, workers, &["--http", &addr, "--viewer-token", VIEWER]);
    let t0 = Instant::now();
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "no dashboard\n{}",
            farm.logs()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    (farm, port)
}

#[test]
fn every_route_needs_a_session_and_the_token_buys_one() {
    let (farm, port) = start("dash-auth", 0);
    let r = request(port, "GET", "/", &[], "");
    assert_eq!((r.status, r.header("location")), (303, Some("/login")));
    for path in [
        "/events",
        "/jobs/job-1/result.exr",
        "/jobs/job-1/preview.png",
    ] {
        assert_eq!(request(port, "GET", path, &[], "").status, 401, "{path}");
    }
    let forged = [("Cookie", "pathfarm_session=0123abcd")];
    assert_eq!(request(port, "GET", "/", &forged, "").status, 303);
    let wrong = request(port, "POST", "/login", &[], "token=not-the-token");
    assert_eq!(wrong.status, 401);
    assert!(
        wrong.text().contains("not the coordinator"),
        "{}",
        wrong.text()
    );
    let login = request(port, "GET", "/login", &[], "");
    assert_eq!(login.status, 200);
    let cookie = sign_in(port);
    let c = [("Cookie", cookie.as_str())];
    let page = request(port, "GET", "/", &c, "");
    assert_eq!(page.status, 200, "{}", farm.logs());
    assert!(page.text().contains("No jobs."), "{}", page.text());
    assert_eq!(page.header("cache-control"), Some("no-store"));
    let csp = page.header("content-security-policy").expect("a CSP");
    assert!(csp.contains("default-src 'self'") && csp.contains("frame-ancestors 'none'"));
    for asset in ["/assets/app.css", "/assets/app.js"] {
        assert_eq!(request(port, "GET", asset, &c, "").status, 200, "{asset}");
    }
    let out = request(port, "POST", "/logout", &c, "");
    assert_eq!(out.status, 303);
    assert_eq!(request(port, "GET", "/", &c, "").status, 303, "signed out");
}

#[test]
fn hostile_paths_and_queries_are_refused_without_echoing_markup() {
    let (_farm, port) = start("dash-hostile", 0);
    let cookie = sign_in(port);
    let c = [("Cookie", cookie.as_str())];
    let r = request(
        port,
        "GET",
        "/?state=%3Cscript%3Ealert(1)%3C/script%3E",
        &c,
        "",
    );
    assert_eq!(r.status, 400);
    assert_eq!(r.header("content-type"), Some("text/plain; charset=utf-8"));
    for path in [
        "/jobs/job-999",
        "/jobs/job-01",
        "/jobs/..%2f..%2fetc%2fpasswd",
        "/jobs/job-1/..%2f..%2fjobs.redb",
        "/assets/..%2fmod.rs",
        "/nowhere",
    ] {
        assert_eq!(request(port, "GET", path, &c, "").status, 404, "{path}");
    }
    let long = format!("/?state={}", "x".repeat(6000));
    let r = request(port, "GET", &long, &c, "");
    assert_eq!(r.status, 400);
    assert!(
        r.body.len() < 1000,
        "the echo is bounded: {} bytes",
        r.body.len()
    );
    let r = request(
        port,
        "POST",
        "/login",
        &[],
        &format!("token={}", "t".repeat(10_000)),
    );
    assert_eq!(r.status, 401);
}

#[test]
fn a_jobs_page_and_downloads_are_the_apis_and_a_job_is_cancelled_from_its_page() {
    let (mut farm, port) = start("dash-jobs", 2);
    farm.wait_registered(2);
    let out = farm.data.join("done.exr");
    submit_ok(&farm, 8, &out, "the first job");
    let cookie = sign_in(port);
    let c = [("Cookie", cookie.as_str())];
    let jobs = request(port, "GET", "/", &c, "");
    assert!(jobs.text().contains("/jobs/job-1"), "{}", jobs.text());
    let done = request(port, "GET", "/?state=done", &c, "");
    assert!(done.text().contains("/jobs/job-1"));
    let failed = request(port, "GET", "/?state=failed", &c, "");
    assert!(!failed.text().contains("/jobs/job-1"));
    let page = request(port, "GET", "/jobs/job-1", &c, "");
    assert_eq!(page.status, 200);
    // The iterations, kept in the job's record once its session is gone: a chart and a
    // table with the training iterations and the final one.
    let rows = page.text().matches("<td>training</td>").count();
    assert!(
        rows >= 2,
        "{rows} training iterations listed:\n{}",
        page.text()
    );
    assert_eq!(page.text().matches("<td>final</td>").count(), 1);
    assert!(page.text().contains("<svg class=\"chart\""));
    // The job's last log lines, from the coordinator's log.
    let log = page
        .text()
        .split("<pre class=\"log\">")
        .nth(1)
        .unwrap_or("")
        .to_string();
    assert!(log.contains("INFO unit finished unit=0"), "{}", page.text());
    for part in ["result.exr", "tree.sdt", "preview.png", "resx=40"] {
        assert!(
            page.text().contains(part),
            "{part} missing:\n{}",
            page.text()
        );
    }
    let exr = request(port, "GET", "/jobs/job-1/result.exr", &c, "");
    assert_eq!(exr.status, 200);
    assert!(
        exr.body == std::fs::read(&out).unwrap(),
        "the EXR is the API's"
    );
    let png = request(port, "GET", "/jobs/job-1/preview.png", &c, "");
    assert!(png.body.starts_with(b"\x89PNG"), "a PNG");
    let guide = request(port, "GET", "/jobs/job-1/guide.png?x=20&y=12", &c, "");
    assert_eq!(guide.status, 200, "{}", guide.text());
    assert!(
        guide.body.starts_with(b"\x89PNG"),
        "the guide's picture is a PNG"
    );
    // Three panels of 256x128 (BSDF sampling, guided mixture, learned quadtree), 8 apart.
    let size = |at: usize| u32::from_be_bytes(guide.body[at..at + 4].try_into().unwrap());
    assert_eq!(
        (size(16), size(20)),
        (3 * 256 + 2 * 8, 128),
        "the PNG's IHDR"
    );
    let outside = request(port, "GET", "/jobs/job-1/guide.png?x=40&y=0", &c, "");
    assert_eq!(outside.status, 404);
    assert!(
        outside.text().contains("outside the 40x24 image"),
        "{}",
        outside.text()
    );
    let hostile = request(port, "GET", "/jobs/job-1/guide.png?x=-1&y=1e9", &c, "");
    assert_eq!(hostile.status, 400);
    let r = request(port, "GET", "/jobs/job-1/guide.png?x=1&y=1", &[], "");
    assert_eq!(r.status, 401);
    let workers = request(port, "GET", "/workers", &c, "");
    assert_eq!(
        workers.text().matches("rendering").count() + workers.text().matches("idle").count(),
        2
    );
    // job-1's tiles are in the last minutes' throughput: a bar chart, and its tiles counted.
    let text = workers.text();
    let legend = text.split("Samples a second accepted").nth(1).unwrap_or("");
    let tiles: u64 = (legend.split(" tiles.").next().unwrap_or(""))
        .rsplit(' ')
        .next()
        .and_then(|n| n.parse().ok())
        .unwrap_or(0);
    assert!(tiles > 0, "the throughput counts job-1's tiles:\n{text}");
    assert!(text.contains("<rect class=\"bar\""), "{text}");

    let long = submit(&farm, 100_000, &farm.data.join("long.exr"), &[]);
    wait_until(&farm, port, &c, "/jobs/job-2", &["training", "final-pass"]);
    let page = request(port, "GET", "/jobs/job-2", &c, "").text();
    let csrf = csrf_of(&page);
    let form = format!("csrf={csrf}");
    let cross = [
        ("Cookie", cookie.as_str()),
        ("Sec-Fetch-Site", "cross-site"),
    ];
    assert_eq!(
        request(port, "POST", "/jobs/job-2/cancel", &cross, &form).status,
        403
    );
    let evil = [
        ("Cookie", cookie.as_str()),
        ("Origin", "http://evil.example"),
    ];
    assert_eq!(
        request(port, "POST", "/jobs/job-2/cancel", &evil, &form).status,
        403
    );
    // Its priority, changed from its page (refused cross-site, with a forged token, for a
    // number that is none) and by `pathfarm priority`.
    let set = |headers: &[(&str, &str)], body: &str| {
        request(port, "POST", "/jobs/job-2/priority", headers, body)
    };
    assert_eq!(set(&cross, &format!("{form}&priority=3")).status, 403);
    assert_eq!(set(&c, "csrf=forged&priority=3").status, 403);
    let bad = set(&c, &format!("{form}&priority=1e99"));
    assert_eq!(bad.status, 400);
    assert!(bad.text().contains("\"1e99\""), "{}", bad.text());
    let r = set(&c, &format!("{form}&priority=7"));
    assert_eq!((r.status, r.header("location")), (303, Some("/jobs/job-2")));
    let shown = |p: i32| {
        let page = request(port, "GET", "/jobs/job-2", &c, "").text();
        page.contains(&format!("<dt>priority</dt><dd>{p}</dd>"))
    };
    assert!(shown(7), "priority 7 not shown");
    let cli = farm.start_client(
        &["priority", "job-2", "-4", "--coordinator", &farm.url],
        &[],
    );
    let out = cli.wait(Duration::from_secs(30));
    assert!(
        out.status.success() && out.stdout.contains("job-2: priority -4"),
        "{} {}",
        out.stdout,
        out.stderr
    );
    assert!(shown(-4), "priority -4 not shown");
    let r = request(port, "POST", "/jobs/job-2/cancel", &c, "csrf=forged");
    assert_eq!(r.status, 403);
    // A viewer sees the page without its forms, and is refused an action even with a valid
    // anti-forgery token.
    let viewer = sign_in_with(port, VIEWER);
    let v = [("Cookie", viewer.as_str())];
    let seen = request(port, "GET", "/jobs/job-2", &v, "").text();
    assert!(seen.contains("you can look, not act") && !seen.contains("name=\"csrf\""));
    let vform = format!("csrf={}", csrf_of(&page));
    let r = request(port, "POST", "/jobs/job-2/cancel", &v, &vform);
    assert_eq!(r.status, 403);
    assert!(r.text().contains("may look, not act"), "{}", r.text());
    assert_eq!(
        request(port, "POST", "/jobs/job-2/cancel", &[], &form).status,
        401
    );
    let origin = format!("http://127.0.0.1:{port}");
    let ok = [("Cookie", cookie.as_str()), ("Origin", origin.as_str())];
    let r = request(port, "POST", "/jobs/job-2/cancel", &ok, &form);
    assert_eq!(
        (r.status, r.header("location")),
        (303, Some("/jobs/job-2")),
        "{}",
        r.text()
    );
    wait_until(&farm, port, &c, "/jobs/job-2", &["cancelled"]);
    let ended = long.wait(Duration::from_secs(60));
    assert!(
        !ended.status.success(),
        "submit --wait of a cancelled job fails"
    );
    farm.workers.clear();
}

/// Live updates: the jobs table's event stream sends the rows at once.
#[test]
fn the_jobs_table_and_the_workers_page_stream_their_content() {
    let (_farm, port) = start("dash-events", 0);
    let cookie = sign_in(port);
    let stream = |path: &str, until: &str| -> String {
        let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let req =
            format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nCookie: {cookie}\r\n\r\n");
        s.write_all(req.as_bytes()).unwrap();
        let mut got = Vec::new();
        let mut buf = [0u8; 4096];
        while !String::from_utf8_lossy(&got).contains(until) {
            let n = s.read(&mut buf).expect("an event within 10 s");
            assert!(n > 0, "the stream ended: {}", String::from_utf8_lossy(&got));
            got.extend_from_slice(&buf[..n]);
        }
        String::from_utf8_lossy(&got).into_owned()
    };
    let text = stream("/events", "No jobs.");
    assert!(text.contains("text/event-stream"), "{text}");
    assert!(text.contains("event: jobs"), "{text}");
    let text = stream("/events?view=workers", "No workers.");
    assert!(text.contains("event: workers"), "{text}");
    assert!(text.contains("Throughput, last 10 minutes"), "{text}");
    let c = [("Cookie", cookie.as_str())];
    let bad = request(port, "GET", "/events?view=%3Cb%3Ex", &c, "");
    assert_eq!(bad.status, 400);
    // (echoed bounded and quoted, as plain text a browser does not render)
    assert_eq!(
        bad.header("content-type"),
        Some("text/plain; charset=utf-8")
    );
    assert!(bad.text().contains("no view"), "{}", bad.text());
    let both = request(port, "GET", "/events?view=workers&job=job-1", &c, "");
    assert_eq!(both.status, 400);
}

/// Polls `path` (at most 60 s) until its page shows one of `states` as the job's state.
fn wait_until(farm: &Farm, port: u16, c: &[(&str, &str)], path: &str, states: &[&str]) {
    let t0 = Instant::now();
    loop {
        let page = request(port, "GET", path, c, "").text();
        if states
            .iter()
            .any(|s| page.contains(&format!(">{s}</span>")))
        {
            return;
        }
        let late = t0.elapsed() > Duration::from_secs(60);
        assert!(!late, "{path} never {states:?}:\n{page}\n{}", farm.logs());
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// With TLS the dashboard is served over TLS with the coordinator's certificate: `curl`
/// with the CA signs in and gets a `Secure` session cookie; plain HTTP gets no page.
#[test]
fn with_tls_the_dashboard_speaks_tls_only_and_its_cookie_is_secure() {
    let dir = crate::common::temp_dir("dash-tls");
    let tls = super::farm::TlsFiles::make(&dir);
    let (listen, port) = (free_port(), free_port());
    let (listen, http) = (format!("127.0.0.1:{listen}"), format!("127.0.0.1:{port}"));
    let data = dir.join("data");
    let args = [
        "coordinator",
        "--listen",
        &listen,
        "--data",
        crate::common::path_str(&data),
        "--http",
        &http,
        "--tls-cert",
        crate::common::path_str(&tls.cert),
        "--tls-key",
        crate::common::path_str(&tls.key),
    ];
    let _coordinator = crate::common::Running::start(&args, &[("PATHFARM_TOKEN", TOKEN)]);
    let t0 = Instant::now();
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t0.elapsed() < Duration::from_secs(30), "no dashboard");
        std::thread::sleep(Duration::from_millis(20));
    }
    let curl = |extra: &[&str]| {
        let out = std::process::Command::new("curl")
            .args(["-sS", "-i", "--max-time", "10", "--cacert"])
            .arg(&tls.ca)
            .args(extra)
            .output()
            .expect("curl (installed by .ci/run)");
        let err = String::from_utf8_lossy(&out.stderr);
        format!("{}{err}", String::from_utf8_lossy(&out.stdout))
    };
    let login = format!("https://127.0.0.1:{port}/login");
    let form = curl(&[&login]);
    assert!(form.starts_with("HTTP/1.1 200"), "{form}");
    let signed = curl(&["--data", &format!("token={TOKEN}"), &login]);
    assert!(signed.starts_with("HTTP/1.1 303"), "{signed}");
    let cookie = (signed.lines())
        .find(|l| l.to_ascii_lowercase().starts_with("set-cookie:"))
        .unwrap_or("");
    assert!(
        cookie.contains("; Secure") && cookie.contains("HttpOnly"),
        "{signed}"
    );
    // Plain HTTP to the TLS port: no HTTP response (a TLS alert, or the connection closed).
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(15))).unwrap();
    s.write_all(b"GET /login HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .unwrap();
    let mut raw = Vec::new();
    let _ = s.read_to_end(&mut raw);
    assert!(
        !raw.starts_with(b"HTTP/"),
        "{}",
        String::from_utf8_lossy(&raw)
    );
}
