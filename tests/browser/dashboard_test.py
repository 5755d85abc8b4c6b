#!/usr/bin/env python3
"""The web dashboard in a real browser: headless Chromium (Debian's chromium and
chromium-driver, driven by selenium) against a real coordinator and two workers on
127.0.0.1. Signs in (a wrong token first), sees a job submitted after the page loaded
appear in the jobs table without a reload, watches a running job's preview change between
iterations and its iterations table and log fill in, clicks a pixel of the preview and gets the
guide's picture, changes a job's priority and cancels it from its page and sees it
cancelled, kills a worker and sees it marked lost, and checks the browser logged no error
on any page.
Screenshots go to target/browser-screenshots/ (not committed).

Usage: python3 tests/browser/dashboard_test.py [--binary target/release/pathfarm]
"""
import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.common.exceptions import StaleElementReferenceException

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
TOKEN = "browser-test-token"
SHOTS = os.path.join(ROOT, "target", "browser-screenshots")


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait(what, predicate, timeout=60.0):
    t0 = time.time()
    while True:
        value = predicate()
        if value:
            return value
        if time.time() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.1)


def browser():
    o = webdriver.ChromeOptions()
    for a in ["--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1280,900",
              "--disable-dev-shm-usage"]:
        o.add_argument(a)
    o.binary_location = shutil.which("chromium") or shutil.which("chromium-browser")
    o.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = shutil.which("chromedriver") or "/usr/lib/chromium/chromedriver"
    return webdriver.Chrome(service=Service(executable_path=driver), options=o)


def no_console_errors(d, page):
    errors = [e for e in d.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, f"{page}: the browser logged errors: {errors}"


def row_state(d, name):
    """The state badge of the workers table's row of worker `name`, or None (also when the
    live updates replace the table while it is read)."""
    try:
        for row in d.find_elements(By.CSS_SELECTOR, "tbody tr"):
            if name in row.text:
                return row.find_element(By.CSS_SELECTOR, "span.state").text
    except StaleElementReferenceException:
        pass
    return None


def shot(d, name, height=None):
    """Saves the window as NAME.png; with `height`, the window that tall for this shot (a
    whole page, for the README's picture)."""
    os.makedirs(SHOTS, exist_ok=True)
    size = d.get_window_size()
    if height:
        d.set_window_size(size["width"], height)
        d.execute_script("window.scrollTo(0, 0)")
    d.save_screenshot(os.path.join(SHOTS, name + ".png"))
    if height:
        d.set_window_size(size["width"], size["height"])


def submit(binary, env, url, scene, spp, res, wait_for_it):
    w, h = res
    args = [binary, "submit", os.path.join(ROOT, "scenes", scene, "scene.xml"), "--coordinator", url,
            "-D", "integrator=guided_path", "-D", f"resx={w}", "-D", f"resy={h}", "--spp", str(spp)]
    return subprocess.Popen(args + (["--wait"] if wait_for_it else []), env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def run(a, tmp, procs):
    env = dict(os.environ, PATHFARM_TOKEN=TOKEN, NO_COLOR="1", RUST_LOG="warn")
    port, http = free_port(), free_port()
    url, web = f"http://127.0.0.1:{port}", f"http://127.0.0.1:{http}"
    procs.append(subprocess.Popen([a.binary, "coordinator", "--listen", f"127.0.0.1:{port}", "--data",
                                   os.path.join(tmp, "coordinator"), "--http", f"127.0.0.1:{http}"],
                                  env=env, stderr=open(os.path.join(tmp, "coordinator.log"), "w")))
    for i in range(2):
        procs.append(subprocess.Popen([a.binary, "worker", "--coordinator", url, "--threads", "1",
                                       "--cache", os.path.join(tmp, f"worker-{i}"), "--name", f"node-{i}"],
                                      env=env, stderr=open(os.path.join(tmp, f"worker-{i}.log"), "w")))
    wait("the dashboard", lambda: socket.socket().connect_ex(("127.0.0.1", http)) == 0)
    d = browser()
    try:
        d.get(web + "/")
        assert d.current_url.endswith("/login"), d.current_url
        d.find_element(By.NAME, "token").send_keys("not-the-token")
        d.find_element(By.CSS_SELECTOR, "form.login button").click()
        wait("the refusal", lambda: "not the coordinator" in d.page_source)
        d.get_log("browser")  # the refusal's 401, deliberate: the checks below start after it
        d.find_element(By.NAME, "token").send_keys(TOKEN)
        d.find_element(By.CSS_SELECTOR, "form.login button").click()
        wait("the jobs page", lambda: d.find_elements(By.ID, "jobs"))
        assert "No jobs." in d.page_source
        # A job submitted now appears without a reload (the table's live updates).
        job1 = submit(a.binary, env, url, "doorway", 96, (240, 135), True)
        procs.append(job1)
        wait("job-1 in the table", lambda: d.find_elements(By.CSS_SELECTOR, "a[href='/jobs/job-1']"))
        shot(d, "jobs")
        no_console_errors(d, "jobs")
        # Its preview changes between iterations, on the open page.
        d.get(web + "/jobs/job-1")
        img = wait("the first preview", lambda: d.find_elements(By.ID, "preview") or d.refresh())
        first = wait("a preview version", lambda: d.find_element(By.ID, "preview").get_attribute("src"))
        wait("the preview to change", lambda: d.find_element(By.ID, "preview").get_attribute("src") != first, 120)
        shot(d, "job-running")
        # The iterations' chart and table, kept current by the live updates.
        wait("an iteration row", lambda: d.find_elements(By.CSS_SELECTOR, "#iterations table.iterations tbody tr"))
        assert d.find_elements(By.CSS_SELECTOR, "#iterations svg.chart rect.bar"), d.page_source
        # The job's log lines, live too.
        wait("a log line", lambda: "unit finished" in d.find_element(By.ID, "log").text)
        # A click on the preview draws the guide at that pixel.
        img = d.find_element(By.ID, "preview")
        d.execute_script("arguments[0].scrollIntoView()", img)
        webdriver.ActionChains(d).move_to_element_with_offset(img, -img.size["width"] // 3, img.size["height"] // 4).click().perform()
        guide = d.find_element(By.ID, "guide")
        wait("the guide's picture", lambda: guide.is_displayed() and d.execute_script(
            "return arguments[0].complete && arguments[0].naturalWidth", guide) == 3 * 256 + 2 * 8)
        assert d.find_element(By.ID, "guide-caption").text.startswith("Pixel "), d.find_element(By.ID, "guide-caption").text
        shot(d, "job-guide")
        shot(d, "job-page", height=1500)
        no_console_errors(d, "job-1")
        # A job cancelled from its page.
        procs.append(submit(a.binary, env, url, "door-ajar", 100000, (64, 36), False))
        wait("job-2", lambda: d.get(web + "/jobs/job-2") or "Cancel the job" in d.page_source)
        d.get_log("browser")  # the 404s of job-2's page before it was submitted
        # Its priority changed from its page.
        field = d.find_element(By.ID, "priority")
        field.clear()
        field.send_keys("5")
        d.find_element(By.CSS_SELECTOR, "form.priority button").click()
        wait("priority 5", lambda: "<dt>priority</dt><dd>5</dd>" in d.page_source)
        d.find_element(By.CSS_SELECTOR, "button.danger").click()
        wait("job-2 cancelled", lambda: ">cancelled</span>" in d.page_source or d.refresh())
        shot(d, "job-cancelled")
        no_console_errors(d, "job-2")
        d.get(web + "/workers")
        assert d.page_source.count("node-") == 2, d.page_source
        assert "Samples a second accepted" in d.page_source, "the farm's throughput chart"
        shot(d, "workers")
        no_console_errors(d, "workers")
        # A killed worker is marked lost (and job-1 still finishes on the other).
        procs[2].kill()
        # (no reload: the page's live updates show it)
        wait("node-1 marked lost", lambda: row_state(d, "node-1") == "lost", 60)
        wait("node-0 still serving", lambda: row_state(d, "node-0") in ("rendering", "idle"), 10)
        shot(d, "workers-lost")
        no_console_errors(d, "workers after the kill")
        assert job1.wait(timeout=300) == 0, "job-1 did not finish"
    finally:
        d.quit()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--binary", default=os.path.join(ROOT, "target", "release", "pathfarm"))
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="pathfarm-browser-")
    procs = []
    try:
        run(a, tmp, procs)
        print("browser test: passed (screenshots in target/browser-screenshots/)")
    except Exception:
        for f in sorted(os.listdir(tmp)):
            if f.endswith(".log"):
                print(f"--- {f}\n" + open(os.path.join(tmp, f)).read()[-3000:], file=sys.stderr)
        raise
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
