"""Upstream client test suites, fetched from package registries at run time
into the cache directory (never committed) and pointed at the broker under
test. Each runner takes a Ctx and returns [(test_id, status, detail)] with
status "pass", "fail" or "skip".

Tests that need RabbitMQ's management plugin, rabbitmqctl, a TLS listener or
Docker are reported as "skip" with the reason from SKIPS (README.md lists
them); so are the few tests RabbitMQ 3.10 itself fails here.
"""

import glob
import json
import os
import re
import shutil
import subprocess
import sys
import urllib.parse
import xml.etree.ElementTree as ET


class SetupError(Exception):
    pass


class Ctx:
    def __init__(self, **kw):
        self.__dict__.update(kw)


def run(cmd, cwd=None, env=None, timeout=1800):
    try:
        return subprocess.run(cmd, cwd=cwd, env=env, timeout=timeout, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    except subprocess.TimeoutExpired as e:
        out = e.stdout.decode("utf-8", "replace") if isinstance(e.stdout, bytes) else (e.stdout or "")
        return subprocess.CompletedProcess(cmd, 124, out + f"\n[timed out after {timeout}s]")


def url_parts(url):
    u = urllib.parse.urlparse(url)
    path = u.path[1:] if u.path.startswith("/") else u.path
    return {
        "host": u.hostname or "127.0.0.1",
        "port": u.port or 5672,
        "user": urllib.parse.unquote(u.username or "guest"),
        "password": urllib.parse.unquote(u.password or "guest"),
        "vhost": urllib.parse.unquote(path) if path else "/",
    }


def fresh(path):
    shutil.rmtree(path, ignore_errors=True)
    os.makedirs(path, exist_ok=True)
    return path


# Reasons for tests that cannot run against any broker started here.
SKIP_PATTERNS = {
    "py-amqp": [
        (r"\[tls", "needs a TLS listener on 5671 with the suite's certificates"),
        (r"test_tls_", "needs a TLS listener on 5671 (and a host named 'rabbitmq')"),
    ],
    "aio-pika": [
        (r"test_leak_unclosed_channel", "flaky against RabbitMQ 3.10 itself: depends on garbage-collection timing"),
        (r"test_reconnect_channel_snapshot::test_create_channels_during_reconnect",
         "flaky against RabbitMQ 3.10 itself: an aiormq close race decided by the connection.close-ok round trip (README item 9)"),
    ],
    "amqprs": [],
}


def skip_reason(suite, test_id):
    for pat, reason in SKIP_PATTERNS.get(suite, []):
        if re.search(pat, test_id):
            return reason
    return None


def junit_results(path, suite):
    out = []
    if not os.path.exists(path):
        return out
    root = ET.parse(path).getroot()
    for tc in root.iter("testcase"):
        tid = f"{tc.get('classname', '')}::{tc.get('name')}"
        failure = tc.find("failure")
        error = tc.find("error")
        skipped = tc.find("skipped")
        reason = skip_reason(suite, tid)
        if reason:
            out.append((tid, "skip", reason))
        elif failure is not None or error is not None:
            node = failure if failure is not None else error
            out.append((tid, "fail", (node.get("message") or "")[:500]))
        elif skipped is not None:
            out.append((tid, "skip", "skipped by the suite itself: " + (skipped.get("message") or "")[:200]))
        else:
            out.append((tid, "pass", None))
    return out


# ---------------------------------------------------------------------------
# PyPI source distributions


def pypi_sdist(ctx, name, version, dirname):
    ctx.ensure_python()
    base = os.path.join(ctx.cache, "pypi")
    os.makedirs(base, exist_ok=True)
    src = os.path.join(base, f"{dirname}-{version}")
    if os.path.isdir(src) and os.path.exists(os.path.join(src, ".complete")):
        return src
    tarballs = glob.glob(os.path.join(base, f"{dirname}-{version}.tar.gz"))
    if not tarballs:
        ctx.log(f"conformance: pip download {name}=={version} (source distribution)")
        r = run([ctx.vpy, "-m", "pip", "download", "-q", "--disable-pip-version-check", "--no-binary", name,
                 "--no-deps", f"{name}=={version}", "-d", base])
        tarballs = glob.glob(os.path.join(base, f"{dirname}-{version}.tar.gz"))
        if r.returncode != 0 or not tarballs:
            raise SetupError(f"pip download --no-binary {name} {name}=={version} failed:\n{r.stdout[-2000:]}")
    shutil.rmtree(src, ignore_errors=True)
    r = run(["tar", "xzf", tarballs[0], "-C", base])
    if r.returncode != 0:
        raise SetupError(f"cannot unpack {tarballs[0]}: {r.stdout}")
    open(os.path.join(src, ".complete"), "w").close()
    return src


def pytest_suite(ctx, suite, src, args, env_extra, timeout=1500):
    xml = os.path.join(ctx.cache, f"{suite}-junit.xml")
    if os.path.exists(xml):
        os.remove(xml)
    env = dict(os.environ, **env_extra)
    env.pop("PYTHONPATH", None)
    r = run([ctx.vpy, "-m", "pytest", "-p", "no:cacheprovider", "-q", f"--junitxml={xml}", *args],
            cwd=src, env=env, timeout=timeout)
    res = junit_results(xml, suite)
    if not res:
        raise SetupError(f"pytest produced no results (exit {r.returncode}):\n{r.stdout[-3000:]}")
    if r.returncode == 124:
        res.append(("(suite)", "fail", "timed out"))
    return res


def run_py_amqp(ctx):
    src = pypi_sdist(ctx, "amqp", "5.4.2", "amqp")
    p = url_parts(ctx.url)
    if p["vhost"] != "/":
        raise SetupError("py-amqp's integration tests use the default vhost '/'")
    return pytest_suite(ctx, "py-amqp", src, ["-o", "addopts=", "-p", "no:asyncio", "t/integration/test_rmq.py"],
                        {"RABBITMQ_HOST": p["host"], "RABBITMQ_5672_TCP": str(p["port"])})


RESET_SCRIPT = """
import sys, amqp
host, port, user, password, vhost = sys.argv[1:6]
c = amqp.Connection(host=f"{host}:{port}", userid=user, password=password, virtual_host=vhost, connect_timeout=10)
c.connect()
for q in sys.argv[6:]:
    ch = c.channel()
    try:
        ch.queue_delete(q)
    except Exception:
        pass
c.close()
"""


def reset_queues(ctx, names):
    """Delete the fixed-name queues a suite leaves behind, as its own CI gets
    a fresh broker container for each run."""
    p = url_parts(ctx.url)
    run([ctx.vpy, "-c", RESET_SCRIPT, p["host"], str(p["port"]), p["user"], p["password"], p["vhost"], *sorted(set(names))], timeout=60)


def run_kombu(ctx):
    src = pypi_sdist(ctx, "kombu", "5.7.0", "kombu")
    p = url_parts(ctx.url)
    text = "".join(open(os.path.join(src, "t", "integration", f)).read() for f in ("common.py", "test_py_amqp.py"))
    reset_queues(ctx, re.findall(r"(?:Queue|SimpleQueue|SimpleBuffer)\(\s*'([\w.]+)'", text))
    return pytest_suite(ctx, "kombu", src, ["-o", "addopts=", "-p", "no:asyncio", "t/integration/test_py_amqp.py"],
                        {"RABBITMQ_HOST": p["host"], "RABBITMQ_5672_TCP": str(p["port"])})


AIO_PIKA_CONFTEST_PATCH = '''

# --- added by leveret conformance/run: the broker under test instead of Docker ---
import os as _lv_os


def pytest_configure(config):  # noqa: F811 - replaces the Docker availability check
    pass


@pytest.fixture(scope="session")
def amqp_direct_url() -> URL:  # noqa: F811 - replaces the Docker container
    return URL(_lv_os.environ["AMQP_URL"])
'''

AIO_PIKA_SKIPPED_FILES = {
    "tests/test_amqps.py": "needs the suite's Docker RabbitMQ with a TLS listener on 5671",
    "tests/test_robust_recovery.py": "stops and restarts the suite's own Docker RabbitMQ container",
}


def run_aio_pika(ctx):
    src = pypi_sdist(ctx, "aio-pika", "10.2.1", "aio_pika")
    conftest = os.path.join(src, "tests", "conftest.py")
    text = open(conftest).read()
    if "leveret conformance" not in text:
        with open(conftest, "a") as f:
            f.write(AIO_PIKA_CONFTEST_PATCH)
    args = ["-p", "no:asyncio", "-o", "log_cli=false", "tests"]
    for path in AIO_PIKA_SKIPPED_FILES:
        args += ["--ignore", path]
    res = pytest_suite(ctx, "aio-pika", src, args, {"AMQP_URL": ctx.url}, timeout=1800)
    for path, reason in AIO_PIKA_SKIPPED_FILES.items():
        res.append((path, "skip", reason))
    return res


# ---------------------------------------------------------------------------
# npm: amqplib's mocha tests


AMQPLIB_BROKER_TESTS = ["test/connect.js", "test/channel_api.js", "test/callback_api.js"]
# Tests that connect to amqp://localhost (or amqp://[::1]) whatever URL says:
# they test the broker under test only when it serves localhost:5672.
AMQPLIB_DEFAULT_ADDRESS_TESTS = {
    "Connect API serverProperties",
    "Connect API using custom heartbeat option",
    "Connect API ipv6",
}


def run_amqplib(ctx):
    ctx.ensure_node()
    base = os.path.join(ctx.cache, "amqplib")
    pkg = os.path.join(base, "package")
    stamp = os.path.join(pkg, ".complete")
    if not os.path.exists(stamp):
        fresh(base)
        ctx.log("conformance: npm pack amqplib@0.10 (with its tests)")
        r = run(["npm", "pack", "amqplib@0.10", "--silent"], cwd=base)
        tgz = glob.glob(os.path.join(base, "amqplib-0.10.*.tgz"))
        if r.returncode != 0 or not tgz:
            raise SetupError(f"npm pack amqplib@0.10 failed:\n{r.stdout[-2000:]}")
        run(["tar", "xzf", tgz[0], "-C", base])
        pj = os.path.join(pkg, "package.json")
        meta = json.load(open(pj))
        mocha = meta.get("devDependencies", {}).get("mocha", "^9.2.2")
        meta.pop("devDependencies", None)  # only mocha is needed to run the tests
        json.dump(meta, open(pj, "w"), indent=1)
        r = run(["npm", "install", "--no-audit", "--no-fund", "--no-save", "--loglevel=error", f"mocha@{mocha}"], cwd=pkg)
        if r.returncode != 0:
            raise SetupError(f"npm install mocha failed:\n{r.stdout[-2000:]}")
        open(stamp, "w").close()
    out = os.path.join(ctx.cache, "amqplib-mocha.json")
    env = dict(os.environ, URL=ctx.url)
    r = run([os.path.join(pkg, "node_modules", ".bin", "mocha"), "-u", "tdd", "--exit", "-R", "json",
             "--reporter-option", f"output={out}", *AMQPLIB_BROKER_TESTS], cwd=pkg, env=env, timeout=900)
    try:
        data = json.load(open(out))
    except (OSError, ValueError):
        raise SetupError(f"mocha produced no report (exit {r.returncode}):\n{r.stdout[-3000:]}")
    res = []
    if not ctx.on_default_address:
        # Drop what they observed: it came from whatever serves localhost:5672.
        why = "connects to localhost:5672 whatever URL says, and the broker under test is elsewhere"
        for kind in ("passes", "failures", "pending"):
            for t in data.get(kind, []):
                if t["fullTitle"] in AMQPLIB_DEFAULT_ADDRESS_TESTS:
                    res.append((t["fullTitle"], "skip", why))
            data[kind] = [t for t in data.get(kind, []) if t["fullTitle"] not in AMQPLIB_DEFAULT_ADDRESS_TESTS]
    for t in data.get("passes", []):
        res.append((t["fullTitle"], "pass", None))
    for t in data.get("failures", []):
        res.append((t["fullTitle"], "fail", (t.get("err") or {}).get("message", "")[:500]))
    for t in data.get("pending", []):
        res.append((t["fullTitle"], "skip", "pending in the suite itself"))
    return res


# ---------------------------------------------------------------------------
# Debian: amqp091-go's integration tests


def run_amqp091_go(ctx):
    ctx.ensure_go()
    debsrc = "/usr/share/gocode/src/github.com/rabbitmq/amqp091-go"
    if not os.path.exists("/usr/share/gocode/src/go.uber.org/goleak"):
        raise SetupError("go.uber.org/goleak is missing (Debian: apt-get install golang-uber-goleak-dev)")
    gopath = os.path.join(ctx.cache, "gopath")
    dst = os.path.join(gopath, "src", "github.com", "rabbitmq", "amqp091-go")
    fresh(os.path.dirname(dst))
    shutil.copytree(debsrc, dst, symlinks=True)
    exe = os.path.join(ctx.cache, "amqp091-go-integration.test")
    env = ctx.go_env(gopath + ":/usr/share/gocode")
    r = run(["go", "test", "-c", "-tags", "integration", "-o", exe, "."], cwd=dst, env=env)
    if r.returncode != 0:
        raise SetupError(f"go test -c -tags integration failed:\n{r.stdout[-3000:]}")
    names = re.findall(r"^func (Test\w+)\(t \*testing\.T\)", open(os.path.join(dst, "integration_test.go")).read(), re.M)
    env = dict(env, AMQP_URL=ctx.url)
    r = run([exe, "-test.v", "-test.count=1", "-test.timeout=900s", "-test.run", "^(" + "|".join(names) + ")$"],
            cwd=dst, env=env, timeout=1000)
    res = {}
    for m in re.finditer(r"^--- (PASS|FAIL|SKIP): (\w+)", r.stdout, re.M):
        res[m.group(2)] = {"PASS": "pass", "FAIL": "fail", "SKIP": "skip"}[m.group(1)]
    out = []
    for n in names:
        st = res.get(n)
        if st is None:
            out.append((n, "fail", "did not run (the test binary stopped early)"))
        elif st == "fail":
            block = re.search(rf"^=== RUN   {n}\n(.*?)^--- FAIL", r.stdout, re.M | re.S)
            out.append((n, "fail", (block.group(1).strip() if block else "")[-500:]))
        elif st == "skip":
            out.append((n, "skip", "skipped by the suite itself"))
        else:
            out.append((n, "pass", None))
    # TestMain wraps the run in goleak.VerifyTestMain: leaked goroutines fail the package.
    if r.returncode != 0 and all(s != "fail" for _, s, _ in out):
        leak = "goleak: " + r.stdout.split("goleak:", 1)[1][:400] if "goleak:" in r.stdout else r.stdout[-500:]
        out.append(("TestMain (goleak.VerifyTestMain)", "fail", leak))
    else:
        out.append(("TestMain (goleak.VerifyTestMain)", "pass" if r.returncode == 0 else "fail", None))
    return out


# ---------------------------------------------------------------------------
# crates.io: lapin's and amqprs's integration tests


CRATES = {"lapin": "2.5.5", "amqprs": "2.1.5"}


def crate_source(ctx, name, version):
    """Fetch the crate through cargo (a scratch project + cargo fetch) and
    copy its source out of cargo's registry into the cache."""
    dst = os.path.join(ctx.cache, "crates", f"{name}-{version}")
    if os.path.exists(os.path.join(dst, ".complete")):
        return dst
    scratch = fresh(os.path.join(ctx.cache, "crates", f"fetch-{name}"))
    with open(os.path.join(scratch, "Cargo.toml"), "w") as f:
        f.write(f'[package]\nname = "fetch-{name}"\nversion = "0.0.0"\nedition = "2021"\n\n[workspace]\n\n'
                f'[dependencies]\n{name} = {{ version = "={version}", default-features = false }}\n')
    os.makedirs(os.path.join(scratch, "src"), exist_ok=True)
    open(os.path.join(scratch, "src", "lib.rs"), "w").close()
    ctx.log(f"conformance: cargo fetch {name} {version} (crates.io source)")
    r = run(["cargo", "fetch", "--quiet"], cwd=scratch)
    if r.returncode != 0:
        raise SetupError(f"cargo fetch of {name} {version} failed:\n{r.stdout[-2000:]}")
    home = os.environ.get("CARGO_HOME", os.path.expanduser("~/.cargo"))
    srcs = glob.glob(os.path.join(home, "registry", "src", "*", f"{name}-{version}"))
    if not srcs:
        raise SetupError(f"{name}-{version} not found under {home}/registry/src after cargo fetch")
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(srcs[0], dst)
    for p in glob.glob(os.path.join(dst, "**"), recursive=True):
        try:
            os.chmod(p, 0o755 if os.path.isdir(p) else 0o644)
        except OSError:
            pass
    # Keep the copy out of any enclosing workspace (conformance/ is inside the repo's).
    with open(os.path.join(dst, "Cargo.toml"), "a") as f:
        f.write("\n[workspace]\n")
    open(os.path.join(dst, ".complete"), "w").close()
    return dst


def cargo_test_targets(ctx, suite, src, targets, env, features_args):
    target_dir = os.path.join(ctx.cache, "cargo-target")
    env = dict(os.environ, CARGO_TARGET_DIR=target_dir, **env)
    test_args = []
    for tname in targets:
        test_args += ["--test", tname]
    ctx.log(f"conformance: cargo test --no-run ({suite} integration tests)")
    r = run(["cargo", "test", "--quiet", "--no-run", *features_args, *test_args], cwd=src, env=env, timeout=2400)
    if r.returncode != 0:
        raise SetupError(f"building {suite}'s tests failed:\n{r.stdout[-3000:]}")
    out = []
    for tname in targets:
        reason = skip_reason(suite, tname)
        if reason:
            out.append((tname, "skip", reason))
            continue
        r = run(["cargo", "test", *features_args, "--test", tname, "--", "--test-threads=1"],
                cwd=src, env=env, timeout=600)
        found = False
        for m in re.finditer(r"^test (\S+) \.\.\. (ok|FAILED|ignored)", r.stdout, re.M):
            found = True
            st = {"ok": "pass", "FAILED": "fail", "ignored": "skip"}[m.group(2)]
            detail = None
            if st == "fail":
                block = re.search(rf"---- {re.escape(m.group(1))} stdout ----\n(.*?)(\n\n|\Z)", r.stdout, re.S)
                detail = (block.group(1) if block else r.stdout[-500:])[-500:]
            out.append((f"{tname}::{m.group(1)}", st, detail if st != "skip" else "ignored by the suite itself"))
        if not found:  # harness = false targets: one result from the exit status
            out.append((tname, "pass" if r.returncode == 0 else "fail", None if r.returncode == 0 else r.stdout[-500:]))
        elif r.returncode not in (0, 101):
            out.append((f"{tname} (process)", "fail", f"exit {r.returncode}: {r.stdout[-300:]}"))
    return out


def run_lapin(ctx):
    src = crate_source(ctx, "lapin", CRATES["lapin"])
    targets = sorted(os.path.splitext(os.path.basename(p))[0] for p in glob.glob(os.path.join(src, "tests", "*.rs")))
    # The tests use no TLS: build without the default rustls feature.
    return cargo_test_targets(ctx, "lapin", src, targets, {"AMQP_ADDR": ctx.url}, ["--no-default-features"])


AMQPRS_ARGS = '''OpenConnectionArguments::new(
        &std::env::var("AMQPRS_HOST").unwrap(),
        std::env::var("AMQPRS_PORT").unwrap().parse().unwrap(),
        &std::env::var("AMQPRS_USER").unwrap(),
        &std::env::var("AMQPRS_PASSWORD").unwrap(),
    )
    .virtual_host(&std::env::var("AMQPRS_VHOST").unwrap())
    .finish()'''


def run_amqprs(ctx):
    src = crate_source(ctx, "amqprs", CRATES["amqprs"])
    common = os.path.join(src, "tests", "common", "mod.rs")
    text = open(common).read()
    # amqprs hard-codes localhost:5672 and user/bitnami: read them from the environment.
    text = text.replace('OpenConnectionArguments::new("localhost", 5672, "user", "bitnami")', AMQPRS_ARGS)
    open(common, "w").write(text)
    consume = os.path.join(src, "tests", "test_consume.rs")
    t2 = open(consume).read().replace('.with_user_id("user")', '.with_user_id(&std::env::var("AMQPRS_USER").unwrap())')
    open(consume, "w").write(t2)
    # The TLS dev-dependency (rustls with aws-lc-rs) is only used with the `tls` feature.
    cargo_toml = os.path.join(src, "Cargo.toml")
    ct = open(cargo_toml).read()
    ct = re.sub(r'\n\[dev-dependencies\.rustls\]\nversion = "[^"]*"\nfeatures = \["aws-lc-rs"\]\n', "\n", ct)
    open(cargo_toml, "w").write(ct)
    targets = re.findall(r'\[\[test\]\]\nname = "(\w+)"', ct)
    p = url_parts(ctx.url)
    env = {"AMQPRS_HOST": p["host"], "AMQPRS_PORT": str(p["port"]), "AMQPRS_USER": p["user"],
           "AMQPRS_PASSWORD": p["password"], "AMQPRS_VHOST": p["vhost"]}
    return cargo_test_targets(ctx, "amqprs", src, targets, env, [])


# name -> (description, runner, in the default run)
SUITES = {
    "up-amqp091-go": ("amqp091-go integration_test.go (Debian source)", run_amqp091_go),
    "up-amqplib": ("amqplib 0.10 mocha tests (npm)", run_amqplib),
    "up-py-amqp": ("py-amqp t/integration/test_rmq.py (PyPI sdist)", run_py_amqp),
    "up-kombu": ("kombu t/integration/test_py_amqp.py (PyPI sdist)", run_kombu),
    "up-lapin": ("lapin tests/ (crates.io)", run_lapin),
    "up-amqprs": ("amqprs tests/ (crates.io)", run_amqprs),
    "up-aio-pika": ("aio-pika tests/ (PyPI sdist)", run_aio_pika),
}
