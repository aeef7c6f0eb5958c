#!/usr/bin/env python3
"""Management API wrong-password flood: usage httpflood.py BINARY PORT"""
import asyncio, base64, os, subprocess, sys, tempfile, time, random
BIN, PORT = sys.argv[1], int(sys.argv[2]); HTTP = PORT + 1
def figs(pid):
    d = {}
    for l in open(f"/proc/{pid}/status"):
        k, _, v = l.partition(":"); d[k] = v.split()
    return int(d["VmRSS"][0]) // 1024, int(d["Threads"][0])
async def req(user, pw, hang=None):
    r, w = await asyncio.open_connection("127.0.0.1", HTTP)
    auth = base64.b64encode(f"{user}:{pw}".encode()).decode()
    w.write(f"GET /api/overview HTTP/1.1\r\nHost: x\r\nAuthorization: Basic {auth}\r\nConnection: close\r\n\r\n".encode())
    await w.drain()
    try:
        if hang: await asyncio.sleep(hang); return None
        line = await r.readline(); return line.split()[1].decode() if line else None
    finally: w.close()
async def main():
    d = tempfile.mkdtemp()
    p = subprocess.Popen([BIN, "--data-dir", d, "--listen", f"127.0.0.1:{PORT}", "--http-listen", f"127.0.0.1:{HTTP}",
        "--metrics-listen", f"127.0.0.1:{PORT+2}", "--log", "error"], stderr=subprocess.DEVNULL)
    await asyncio.sleep(3)
    print("legit first:", await req("guest", "guest"), "idle", figs(p.pid))
    stop = time.monotonic() + 10; peak = [0, 0]; n = 0; lat = []
    async def flood():
        nonlocal n
        while time.monotonic() < stop:
            try: await req("guest", f"w{random.random()}", 0.03)
            except Exception: pass
            n += 1
    async def sample():
        while time.monotonic() < stop + 0.5:
            a, b = figs(p.pid); peak[0] = max(peak[0], a); peak[1] = max(peak[1], b); await asyncio.sleep(0.25)
    async def legit():
        await asyncio.sleep(1)
        while time.monotonic() < stop - 1:
            t = time.monotonic()
            try: s = await asyncio.wait_for(req("guest", "guest"), 15)
            except Exception as e: s = repr(e)
            lat.append((round((time.monotonic() - t) * 1000), s)); await asyncio.sleep(1)
    await asyncio.gather(sample(), legit(), *[flood() for _ in range(60)])
    print(f"requests {n}; peak rss {peak[0]} MB threads {peak[1]}; legit (ms, status): {lat}")
    await asyncio.sleep(3); print("after +3s", figs(p.pid)); p.terminate(); p.wait()
asyncio.run(main())
