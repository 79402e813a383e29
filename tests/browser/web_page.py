#!/usr/bin/env python3
"""The web page in a real browser (headless Chromium driven by Selenium) against a live farm.

Starts a coordinator (with a token) and two workers from target/release/tessera, loads the page,
enters the token, submits scenes through the form, and checks the DOM: rows appear and update in
place, thumbnails load at their shown size, the job page shows the preview (and exposure changes
it), the per-tile heat map, the error chart and the events log; an error message stays until
dismissed; the workers page drains and resumes a worker. Screenshots go to docs/web/ with
--screenshots. With --traffic N it also measures the bytes the page receives per minute while N
jobs run (Chrome's network log), for this page and for the previous polling page (--old-page FILE,
served through a small proxy).

Prints "browser: P passed, F failed" and exits non-zero on a failure.

Needs: chromium and chromium-driver (Debian), selenium (PyPI); .ci/run installs them.
"""
import argparse
import http.server
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

from selenium import webdriver
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TESSERA = os.path.join(ROOT, "target", "release", "tessera")
TOKEN = "browser-test-token"
results = []


def check(name, cond, detail=""):
    results.append((name, bool(cond)))
    print(("ok   " if cond else "FAIL ") + name + ("" if cond else f": {detail}"), flush=True)
    return cond


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def api(url, path, method="GET", data=None):
    req = urllib.request.Request(url + "/api/v1" + path, method=method, data=data,
                                 headers={"Authorization": "Bearer " + TOKEN})
    with urllib.request.urlopen(req, timeout=30) as r:
        return json.loads(r.read() or b"null")


class Farm:
    def __init__(self, tmp):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = dict(os.environ, TESSERA_TOKEN=TOKEN, TESSERA_LOG="warn")
        log = open(os.path.join(tmp, "coordinator.log"), "w")
        self.procs = [subprocess.Popen([TESSERA, "coordinator", "--listen", f"127.0.0.1:{self.port}",
                                        "--data-dir", os.path.join(tmp, "data")], env=env, stdout=log, stderr=log)]
        for _ in range(100):
            try:
                urllib.request.urlopen(self.url + "/healthz", timeout=1)
                break
            except Exception:
                time.sleep(0.1)
        for i in range(2):
            wlog = open(os.path.join(tmp, f"worker{i}.log"), "w")
            self.procs.append(subprocess.Popen([TESSERA, "worker", "--coordinator", self.url, "--threads", "1",
                                                "--name", f"worker{i}"], env=env, stdout=wlog, stderr=wlog))

    def stop(self):
        for p in self.procs:
            p.kill()
            p.wait()


def browser(log_network=False):
    opts = webdriver.ChromeOptions()
    for a in ["--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1400,1000"]:
        opts.add_argument(a)
    if log_network:
        opts.set_capability("goog:loggingPrefs", {"performance": "ALL"})
    service = webdriver.ChromeService(executable_path=shutil.which("chromedriver") or "/usr/bin/chromedriver")
    return webdriver.Chrome(options=opts, service=service)


def wait(driver, what, timeout=60):
    return WebDriverWait(driver, timeout, poll_frequency=0.2).until(lambda d: what(d))


def submit_form(d, scene, **fields):
    d.get(d.current_url.split("#")[0] + "#/")
    form = d.find_element(By.ID, "submit")
    for name in ["spp", "width", "height", "noise_target", "min_spp", "time_budget", "frames", "name", "seed", "camera"]:
        el = form.find_element(By.NAME, name)
        el.clear()
        if name in fields:
            el.send_keys(str(fields[name]))
    form.find_element(By.NAME, "scene").send_keys(scene)
    before = d.find_element(By.ID, "submitted").text
    form.find_element(By.ID, "submit-button").click()
    wait(d, lambda d: d.find_element(By.ID, "submitted").text != before or d.find_element(By.ID, "msg").is_displayed(), 30)
    text = d.find_element(By.ID, "submitted").text
    if text == before:
        print("submission refused:", d.find_element(By.ID, "msg").text, flush=True)
        return None
    return text.replace("submitted ", "")


def run_checks(farm, shots_dir):
    d = browser()
    try:
        d.get(farm.url + "/")
        d.find_element(By.ID, "token").send_keys(TOKEN)
        d.execute_script("document.getElementById('token').dispatchEvent(new Event('change'))")
        wait(d, lambda d: d.find_element(By.ID, "live").text == "live", 20)
        check("the page connects to the event stream", True)
        scene = os.path.join(ROOT, "scenes", "blender", "materials.glb")

        # A fixed-spp job through the form: its row appears, updates in place and ends done.
        job = submit_form(d, scene, spp=16, width=96, name="form job")
        check("the form submits a job", job and job.startswith("j"), job)
        row_sel = f"tr[data-job='{job}']"
        wait(d, lambda d: d.find_elements(By.CSS_SELECTOR, row_sel), 20)
        row = d.find_element(By.CSS_SELECTOR, row_sel)
        wait(d, lambda d: "done" in d.find_element(By.CSS_SELECTOR, row_sel).text, 120)
        check("the row updated in place to done (same element)",
              d.find_element(By.CSS_SELECTOR, row_sel) == row)
        thumb = row.find_element(By.CSS_SELECTOR, "img.thumb")
        wait(d, lambda d: d.execute_script("return arguments[0].naturalWidth", thumb) > 0, 30)
        nw = d.execute_script("return arguments[0].naturalWidth", thumb)
        check("the thumbnail is downloaded at the size shown (<= 160 px)", 0 < nw <= 160, nw)
        check("the form's name reached the job", "form job" in row.text, row.text)

        # A noise-target job: the job page's heat map, chart, events and exposure.
        job2 = submit_form(d, scene, noise_target=0.05, min_spp=16, width=128, name="target job")
        check("a noise-target job is submitted", job2, job2)
        d.get(farm.url + f"/#/job/{job2}")
        wait(d, lambda d: d.find_element(By.ID, "job-title").text.startswith("Job " + job2), 20)
        wait(d, lambda d: "done" in d.find_element(By.ID, "job-summary").text, 180)
        wait(d, lambda d: int(d.find_element(By.ID, "heat").get_attribute("data-tiles") or 0) > 0, 20)
        tiles = int(d.find_element(By.ID, "heat").get_attribute("data-tiles"))
        check("the heat map draws every tile", tiles == 4 * 3, tiles)  # 128x96 in 32 px tiles
        wait(d, lambda d: d.find_elements(By.ID, "chart-svg"), 20)
        points = int(d.find_element(By.ID, "chart-svg").get_attribute("data-points"))
        check("the error chart has points", points >= 1, points)
        kinds = [r.get_attribute("data-kind") for r in d.find_elements(By.CSS_SELECTOR, "#events tbody tr")]
        check("the events log shows submitted, workers joining and done",
              "submitted" in kinds and "done" in kinds and "worker_joined" in kinds, kinds)
        big = d.find_element(By.ID, "big")
        wait(d, lambda d: d.execute_script("return arguments[0].naturalWidth", big) > 0, 30)

        def mean_brightness():
            return d.execute_script("""
              const img = document.getElementById('big'), c = document.createElement('canvas');
              c.width = img.naturalWidth; c.height = img.naturalHeight;
              const x = c.getContext('2d'); x.drawImage(img, 0, 0);
              const p = x.getImageData(0, 0, c.width, c.height).data; let s = 0;
              for (let i = 0; i < p.length; i += 4) s += p[i] + p[i + 1] + p[i + 2];
              return s / (p.length / 4);""")
        b0 = mean_brightness()
        src0 = big.get_attribute("src")
        d.execute_script("const e = document.getElementById('exposure'); e.value = 2; e.dispatchEvent(new Event('input'))")
        wait(d, lambda d: d.find_element(By.ID, "big").get_attribute("src") != src0, 20)
        wait(d, lambda d: d.execute_script("return document.getElementById('big').complete"), 10)
        b2 = mean_brightness()
        check("exposure +2 brightens the preview", b2 > 1.3 * b0, (b0, b2))
        d.find_element(By.CSS_SELECTOR, "button[data-zoom='2']").click()
        w2 = d.execute_script("return document.getElementById('big').getBoundingClientRect().width")
        check("zoom 2x doubles the preview's width", abs(w2 - 2 * 128) < 2, w2)
        if shots_dir:
            d.execute_script("const e = document.getElementById('exposure'); e.value = 0; e.dispatchEvent(new Event('input'))")
            d.find_element(By.CSS_SELECTOR, "button[data-zoom='fit']").click()
            time.sleep(1.5)
            d.save_screenshot(os.path.join(shots_dir, "job.png"))

        # Resubmit from the job page opens the new job.
        d.find_element(By.CSS_SELECTOR, f"button[data-resubmit='{job2}']").click()
        wait(d, lambda d: f"#/job/j" in d.current_url and job2 not in d.current_url, 20)
        check("resubmit opens the new job's page", job2 not in d.current_url, d.current_url)

        # A refused submission: the message stays after live updates.
        d.get(farm.url + "/#/")
        submit_form(d, scene, width=100000)
        msg = d.find_element(By.ID, "msg")
        check("a refused submission shows its error", msg.is_displayed() and "width" in msg.text, msg.text)
        time.sleep(3)
        check("the error is still shown after 3 s of updates", msg.is_displayed(), msg.text)
        d.find_element(By.ID, "msg-close").click()
        check("the error is dismissed with ×", not msg.is_displayed())
        if shots_dir:
            time.sleep(1)
            d.save_screenshot(os.path.join(shots_dir, "jobs.png"))

        # Workers: two listed; drain one, it says draining; resume.
        d.get(farm.url + "/#/workers")
        wait(d, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#workers tbody tr")) == 2, 20)
        wid = d.find_elements(By.CSS_SELECTOR, "#workers tbody tr")[0].get_attribute("data-worker")
        check("worker ids start with the names given", wid.startswith("worker"), wid)
        d.find_element(By.CSS_SELECTOR, f"#workers tr[data-worker='{wid}'] button[data-drain]").click()
        sel = f"#workers tr[data-worker='{wid}'] .wstate"
        wait(d, lambda d: d.find_element(By.CSS_SELECTOR, sel).text == "draining", 20)
        check("drain from the page", True)
        if shots_dir:
            d.save_screenshot(os.path.join(shots_dir, "workers.png"))
        d.find_element(By.CSS_SELECTOR, f"#workers tr[data-worker='{wid}'] button[data-resume]").click()
        wait(d, lambda d: d.find_element(By.CSS_SELECTOR, sel).text in ("idle", "busy"), 20)
        check("resume from the page", True)
        # Network errors are expected (401 before the token, the refused 422); script errors are not.
        errors = [e for e in d.get_log("browser") if e["level"] == "SEVERE" and e.get("source") != "network"]
        check("no script errors in the console", not errors, errors)
    finally:
        d.quit()


class OldPageProxy(http.server.BaseHTTPRequestHandler):
    """Serves a previous version of the page at / and forwards everything else to the farm."""
    page = b""
    upstream = ""

    def do_GET(self):
        if self.path == "/":
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(self.page)))
            self.end_headers()
            self.wfile.write(self.page)
            return
        req = urllib.request.Request(self.upstream + self.path,
                                     headers={k: v for k, v in self.headers.items() if k.lower() == "authorization"})
        try:
            with urllib.request.urlopen(req, timeout=30) as r:
                body, status, ctype = r.read(), r.status, r.headers.get("Content-Type", "")
        except urllib.error.HTTPError as e:
            body, status, ctype = e.read(), e.code, e.headers.get("Content-Type", "")
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *a):
        pass


def traffic(farm, n_jobs, url, seconds):
    """Bytes the page at `url` receives in `seconds` while `n_jobs` jobs run."""
    scene = os.path.join(ROOT, "scenes", "blender", "materials.glb")
    ids = []
    for i in range(n_jobs):
        with open(scene, "rb") as f:
            data = f.read()
        boundary = "tesseraboundary"
        settings = json.dumps({"width": 640, "height": 480, "spp": 4096, "name": f"traffic {i}"}).encode()
        body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"scene\"; filename=\"materials.glb\"\r\n"
                f"Content-Type: application/octet-stream\r\n\r\n").encode() + data + \
               (f"\r\n--{boundary}\r\nContent-Disposition: form-data; name=\"settings\"\r\n\r\n").encode() + settings + \
               f"\r\n--{boundary}--\r\n".encode()
        req = urllib.request.Request(farm.url + "/api/v1/jobs", data=body, method="POST", headers={
            "Authorization": "Bearer " + TOKEN, "Content-Type": f"multipart/form-data; boundary={boundary}"})
        ids.append(json.loads(urllib.request.urlopen(req).read())["id"])
    d = browser(log_network=True)
    try:
        d.get(url)
        d.execute_script(f"localStorage.setItem('tessera-token', '{TOKEN}')")
        d.get(url)
        time.sleep(5)
        d.get_log("performance")  # drop the page load
        time.sleep(seconds)
        total = 0
        requests = set()
        for entry in d.get_log("performance"):
            m = json.loads(entry["message"])["message"]
            if m["method"] == "Network.dataReceived":
                total += m["params"].get("encodedDataLength", 0) or m["params"].get("dataLength", 0)
            if m["method"] == "Network.requestWillBeSent":
                requests.add(m["params"]["requestId"] + str(m["params"].get("timestamp")))
        running = sum(1 for j in api(farm.url, "/jobs")["jobs"] if j["id"] in ids and j["state"] == "running")
        return total, len(requests), running
    finally:
        d.quit()
        for i in ids:
            api(farm.url, f"/jobs/{i}", method="DELETE")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--screenshots", help="directory for the screenshots (e.g. docs/web)")
    ap.add_argument("--traffic", type=int, default=0, help="also measure traffic with this many running jobs")
    ap.add_argument("--seconds", type=float, default=60)
    ap.add_argument("--old-page", help="a previous page's HTML to measure beside this one")
    args = ap.parse_args()
    if args.screenshots:
        os.makedirs(args.screenshots, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix="tessera-browser-")
    farm = Farm(tmp)
    try:
        run_checks(farm, args.screenshots)
        if args.traffic:
            new = traffic(farm, args.traffic, farm.url + "/", args.seconds)
            print(f"traffic, this page: {new[0] / 1e6:.3f} MB in {args.seconds:.0f} s, {new[1]} requests, {new[2]} jobs running")
            if args.old_page:
                OldPageProxy.page = open(args.old_page, "rb").read()
                OldPageProxy.upstream = farm.url
                port = free_port()
                srv = http.server.ThreadingHTTPServer(("127.0.0.1", port), OldPageProxy)
                threading.Thread(target=srv.serve_forever, daemon=True).start()
                old = traffic(farm, args.traffic, f"http://127.0.0.1:{port}/", args.seconds)
                srv.shutdown()
                print(f"traffic, old page: {old[0] / 1e6:.3f} MB in {args.seconds:.0f} s, {old[1]} requests, {old[2]} jobs running")
    except Exception as e:  # a timeout or a missing element is a failure, reported as such
        check("browser session", False, repr(e))
    finally:
        farm.stop()
    passed = sum(1 for _, ok in results if ok)
    failed = len(results) - passed
    print(f"browser: {passed} passed, {failed} failed")
    if failed:
        for f in ("coordinator.log", "worker0.log"):
            p = os.path.join(tmp, f)
            if os.path.exists(p):
                print(f"--- {f}\n" + open(p).read()[-3000:])
        sys.exit(1)
    shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
