//! What `/proc` says about a local broker: its resident memory
//! (`VmRSS`), its CPU time, and which process listens on a TCP port (the
//! socket's inode in `/proc/net/tcp*`, then the process holding it among
//! `/proc/*/fd`; needs the right to read the broker's fds, i.e. the same
//! user or root). `pgrep`-style lookup by name is the fallback. And what
//! it says about the machine: busy CPU time, the load average and CPU
//! pressure, to record how loaded it was during a run.

use serde::Serialize;
use std::fs;
use std::time::Instant;

/// Clock ticks per second of `/proc/*/stat` times (`USER_HZ`, 100 on
/// every Linux architecture that matters here).
const TICKS_PER_SECOND: f64 = 100.0;

/// Resident memory of a process, bytes.
pub fn rss_bytes(pid: u32) -> Option<u64> {
    let status = fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// User plus system CPU time of a process, seconds.
pub fn cpu_seconds(pid: u32) -> Option<f64> {
    let stat = fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name may hold spaces and parentheses: fields are counted
    // from the last ')'.
    let rest = &stat[stat.rfind(')')? + 1..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // After ')': state is field 3, utime field 14, stime field 15.
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    Some((utime + stime) / TICKS_PER_SECOND)
}

/// Measures a process's CPU use over an interval.
#[derive(Debug, Clone, Copy)]
pub struct CpuMeter {
    pid: u32,
    start_cpu: f64,
    start: Instant,
}

impl CpuMeter {
    /// Starts measuring `pid`, if its stat is readable.
    pub fn start(pid: u32) -> Option<Self> {
        Some(CpuMeter {
            pid,
            start_cpu: cpu_seconds(pid)?,
            start: Instant::now(),
        })
    }

    /// CPU use since the start, in percent of one core.
    pub fn percent(&self) -> Option<f64> {
        let used = cpu_seconds(self.pid)? - self.start_cpu;
        let elapsed = self.start.elapsed().as_secs_f64();
        (elapsed > 0.0).then(|| 100.0 * used / elapsed)
    }
}

/// CPU time of the whole machine (every core) spent on anything but
/// idle and iowait, seconds (`/proc/stat`).
pub fn machine_busy_seconds() -> Option<f64> {
    let stat = fs::read_to_string("/proc/stat").ok()?;
    let line = stat.lines().find(|l| l.starts_with("cpu "))?;
    let ticks: Vec<u64> = line
        .split_whitespace()
        .skip(1)
        .filter_map(|f| f.parse().ok())
        .collect();
    // user nice system idle iowait irq softirq steal …
    let busy: u64 = ticks
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != 3 && *i != 4 && *i < 8)
        .map(|(_, t)| *t)
        .sum();
    Some(busy as f64 / TICKS_PER_SECOND)
}

/// Measures the machine's CPU use over an interval.
#[derive(Debug, Clone, Copy)]
pub struct MachineMeter {
    start_busy: f64,
    start: Instant,
}

impl MachineMeter {
    /// Starts measuring.
    pub fn start() -> Option<Self> {
        Some(MachineMeter {
            start_busy: machine_busy_seconds()?,
            start: Instant::now(),
        })
    }

    /// CPU use of every process since the start, in percent of one core.
    pub fn percent(&self) -> Option<f64> {
        let used = machine_busy_seconds()? - self.start_busy;
        let elapsed = self.start.elapsed().as_secs_f64();
        (elapsed > 0.0).then(|| 100.0 * used / elapsed)
    }
}

/// How loaded the machine is: the load averages and, where the kernel
/// reports pressure stall information, the share of time some task waited
/// for a CPU.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct MachineLoad {
    /// Runnable and uninterruptible tasks, averaged over 1, 5 and 15
    /// minutes (`/proc/loadavg`).
    pub load_average: [f64; 3],
    /// Percent of the last ten seconds in which at least one task waited
    /// for a CPU (`/proc/pressure/cpu`, `some avg10`).
    pub cpu_pressure_avg10: Option<f64>,
}

impl MachineLoad {
    /// Reads both, if `/proc/loadavg` is there.
    pub fn now() -> Option<Self> {
        let text = fs::read_to_string("/proc/loadavg").ok()?;
        let mut fields = text.split_whitespace().map(str::parse::<f64>);
        let mut load_average = [0.0; 3];
        for slot in &mut load_average {
            *slot = fields.next()?.ok()?;
        }
        Some(MachineLoad {
            load_average,
            cpu_pressure_avg10: cpu_pressure_avg10(),
        })
    }
}

impl std::fmt::Display for MachineLoad {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let [one, five, fifteen] = self.load_average;
        write!(f, "load average {one:.2} {five:.2} {fifteen:.2}")?;
        if let Some(pressure) = self.cpu_pressure_avg10 {
            write!(f, ", CPU pressure {pressure:.1}%")?;
        }
        Ok(())
    }
}

/// `some avg10` of `/proc/pressure/cpu`: "some avg10=1.23 avg60=… total=…".
fn cpu_pressure_avg10() -> Option<f64> {
    let text = fs::read_to_string("/proc/pressure/cpu").ok()?;
    let some = text.lines().find(|l| l.starts_with("some"))?;
    some.split_whitespace()
        .find_map(|field| field.strip_prefix("avg10="))?
        .parse()
        .ok()
}

/// The inodes of sockets listening on `port` (IPv4 and IPv6).
fn listening_inodes(port: u16) -> Vec<u64> {
    let mut inodes = Vec::new();
    for table in ["/proc/net/tcp", "/proc/net/tcp6"] {
        let Ok(text) = fs::read_to_string(table) else {
            continue;
        };
        for line in text.lines().skip(1) {
            let fields: Vec<&str> = line.split_whitespace().collect();
            if fields.len() < 10 || fields[3] != "0A" {
                continue;
            }
            let Some(local_port) = fields[1]
                .rsplit(':')
                .next()
                .and_then(|p| u16::from_str_radix(p, 16).ok())
            else {
                continue;
            };
            if local_port == port {
                if let Ok(inode) = fields[9].parse() {
                    inodes.push(inode);
                }
            }
        }
    }
    inodes
}

/// The process listening on a local TCP port.
pub fn pid_listening_on(port: u16) -> Option<u32> {
    let inodes = listening_inodes(port);
    if inodes.is_empty() {
        return None;
    }
    let targets: Vec<String> = inodes.iter().map(|i| format!("socket:[{i}]")).collect();
    for (pid, dir) in processes() {
        let Ok(fds) = fs::read_dir(dir.join("fd")) else {
            continue;
        };
        for fd in fds.flatten() {
            if let Ok(link) = fs::read_link(fd.path()) {
                if targets.iter().any(|t| link.as_os_str() == t.as_str()) {
                    return Some(pid);
                }
            }
        }
    }
    None
}

/// Every process: its pid and its /proc directory.
fn processes() -> impl Iterator<Item = (u32, std::path::PathBuf)> {
    fs::read_dir("/proc")
        .into_iter()
        .flat_map(|dir| dir.flatten())
        .filter_map(|entry| {
            let pid = entry.file_name().to_str()?.parse::<u32>().ok()?;
            Some((pid, entry.path()))
        })
}

/// Processes whose command name is `name` (as `pgrep -x` would).
pub fn pids_named(name: &str) -> Vec<u32> {
    let mut pids = Vec::new();
    for (pid, dir) in processes() {
        if let Ok(comm) = fs::read_to_string(dir.join("comm")) {
            if comm.trim_end() == name {
                pids.push(pid);
            }
        }
    }
    pids.sort_unstable();
    pids
}

/// The broker process behind an AMQP URL: whoever listens on its port if
/// the host is local, else the only `beam.smp` or `leveret` process.
pub fn find_broker_pid(url: &str) -> Option<u32> {
    let options = leveret_client::ConnectionOptions::from_uri(url).ok()?;
    let local = matches!(
        options.host.as_str(),
        "localhost" | "127.0.0.1" | "::1" | "0.0.0.0"
    );
    if local {
        if let Some(pid) = pid_listening_on(options.port) {
            return Some(pid);
        }
    }
    for name in ["beam.smp", "leveret"] {
        if let [pid] = pids_named(name)[..] {
            return Some(pid);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_our_own_process() {
        let me = std::process::id();
        assert!(rss_bytes(me).unwrap() > 0);
        assert!(cpu_seconds(me).is_some());
        assert!(CpuMeter::start(me).is_some());
        assert!(MachineMeter::start().is_some());
        let load = MachineLoad::now().expect("/proc/loadavg");
        assert!(load.load_average.iter().all(|l| *l >= 0.0));
        assert!(load.to_string().starts_with("load average "));
    }

    #[test]
    fn finds_the_listener_of_a_port() {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        assert_eq!(pid_listening_on(port), Some(std::process::id()));
    }
}
