//! Hosts for the multi-host system test: Linux network namespaces on a bridge, each a machine of
//! its own (the router, the station, each robot, the observer), with links that can be cut.
//!
//! The bridge lives in a namespace of its own, so nothing of the test touches the machine's own
//! network: each host has one interface, `eth0`, a veth whose peer is a port of that bridge, an
//! address of [`SUBNET`]`.0/24` and no default route; every process listens on its host's own
//! address or on its loopback, never on all interfaces. Names carry the test's pid and a counter, so
//! an earlier run that was killed before it could clean up cannot collide; [`Hosts::new`] removes
//! what such runs left behind (namespaces of this prefix whose pid is gone).
//!
//! Processes run as `ip netns exec NS env RUST_LOG=.. sh -c 'exec "$0" "$@" >&2' BINARY ARGS...`
//! (zenohd logs to stdout); `ip`, `env` and `sh` each exec the next, so the child's pid is the
//! binary's own ([`pid_in`] finds it and checks that). Dropping [`Hosts`]
//! kills whatever still runs in its namespaces and deletes them, also when the test panics.

use std::collections::BTreeMap;
use std::net::Ipv4Addr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use prost::Message;
use proto::GlobalMap;

use crate::{Process, describe, tails};

/// The hosts' network: `10.213.7.0/24`, private, and reachable only inside the test's namespaces.
pub const SUBNET: &str = "10.213.7";

/// Prefix of every namespace the test makes.
const PREFIX: &str = "emrh-";

/// Hosts made by this process so far (a part of each run's names).
static RUNS: AtomicUsize = AtomicUsize::new(0);

/// A set of hosts on one bridge; dropping it removes them all.
pub struct Hosts {
    tag: String,
    bridge: String,
    hosts: BTreeMap<String, Ipv4Addr>,
}

impl Hosts {
    /// A bridge in a namespace of its own, no host yet.
    pub fn new() -> Hosts {
        remove_leftovers();
        let tag = format!("{PREFIX}{}-{}", std::process::id(), RUNS.fetch_add(1, Ordering::SeqCst));
        let hosts = Hosts { bridge: format!("{tag}-bridge"), tag, hosts: BTreeMap::new() };
        ip(&["netns", "add", &hosts.bridge]);
        hosts.quiet(&hosts.bridge);
        ip(&["-n", &hosts.bridge, "link", "add", "br0", "type", "bridge"]);
        ip(&["-n", &hosts.bridge, "link", "set", "br0", "up"]);
        hosts
    }

    /// The namespace of host `name`.
    pub fn netns(&self, name: &str) -> String {
        format!("{}-{name}", self.tag)
    }

    /// The namespace of the bridge.
    pub fn bridge_netns(&self) -> &str {
        &self.bridge
    }

    /// The bridge's port for host `name` (an interface of the bridge's namespace).
    pub fn port(name: &str) -> String {
        let port = format!("p-{name}");
        assert!(port.len() <= 15, "interface name {port} is too long");
        port
    }

    /// Adds host `name` at [`SUBNET`]`.octet`, its link up; returns its address.
    pub fn add(&mut self, name: &str, octet: u8) -> Ipv4Addr {
        let addr: Ipv4Addr = format!("{SUBNET}.{octet}").parse().expect("an address");
        let ns = self.netns(name);
        let port = Hosts::port(name);
        ip(&["netns", "add", &ns]);
        self.quiet(&ns);
        ip(&["link", "add", "eth0", "netns", &ns, "type", "veth", "peer", "name", &port, "netns", &self.bridge]);
        ip(&["-n", &self.bridge, "link", "set", &port, "master", "br0", "up"]);
        // Frames of at most one MTU, as on a wire between machines: a veth passes 64 kB GSO
        // super-packets otherwise, and a rule dropping "a packet" would drop dozens of segments.
        ip(&["-n", &ns, "link", "set", "eth0", "gso_max_segs", "1", "gso_max_size", "1500"]);
        ip(&["-n", &ns, "addr", "add", &format!("{addr}/24"), "dev", "eth0"]);
        ip(&["-n", &ns, "link", "set", "eth0", "up"]);
        ip(&["-n", &ns, "link", "set", "lo", "up"]);
        self.hosts.insert(name.to_owned(), addr);
        addr
    }

    /// Removes host `name`: kills what runs in it and deletes its namespace (its link goes with it).
    pub fn remove(&mut self, name: &str) {
        let ns = self.netns(name);
        kill_all_in(&ns);
        ip(&["netns", "del", &ns]);
        self.hosts.remove(name);
    }

    /// The address of host `name`.
    pub fn addr(&self, name: &str) -> Ipv4Addr {
        *self.hosts.get(name).unwrap_or_else(|| panic!("no host {name}"))
    }

    /// Cuts host `name`'s link at the bridge, as a pulled cable: its interface stays up with no
    /// carrier, and nothing it sends arrives or reaches it.
    pub fn cut(&self, name: &str) {
        ip(&["-n", &self.bridge, "link", "set", &Hosts::port(name), "down"]);
    }

    /// Puts host `name`'s link back.
    pub fn restore(&self, name: &str) {
        ip(&["-n", &self.bridge, "link", "set", &Hosts::port(name), "up"]);
    }

    /// Loads an nftables ruleset into namespace `ns`.
    pub fn nft(&self, ns: &str, ruleset: &str) {
        let mut child = Command::new("ip")
            .args(["netns", "exec", ns, "nft", "-f", "-"])
            .stdin(Stdio::piped())
            .spawn()
            .expect("run nft");
        std::io::Write::write_all(child.stdin.as_mut().expect("nft's stdin"), ruleset.as_bytes()).expect("to nft");
        drop(child.stdin.take());
        let status = child.wait().expect("nft");
        assert!(status.success(), "nft refused the ruleset:\n{ruleset}");
    }

    /// `nft list ...` in namespace `ns`.
    pub fn nft_list(&self, ns: &str, what: &[&str]) -> String {
        let out = Command::new("ip").args(["netns", "exec", ns, "nft", "list"]).args(what).output().expect("run nft");
        assert!(out.status.success(), "nft list {what:?}: {}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// Starts `binary args...` on host `name`, its stdout and stderr into `log_dir/<label>.log`, with
    /// `RUST_LOG=log_filter` (`info` when `None`). `env` and `sh` exec in turn, as `ip netns exec`
    /// does: the process's pid is the binary's.
    pub fn start(
        &self,
        name: &str,
        label: &str,
        binary: &Path,
        args: &[String],
        log_filter: Option<&str>,
        log_dir: &Path,
    ) -> Process {
        assert!(self.hosts.contains_key(name), "no host {name}");
        let mut full: Vec<String> = ["netns", "exec", &self.netns(name), "env"].map(String::from).to_vec();
        full.push(format!("RUST_LOG={}", log_filter.unwrap_or("info")));
        full.extend(["sh", "-c", r#"exec "$0" "$@" >&2"#].map(String::from));
        full.push(binary.display().to_string());
        full.extend_from_slice(args);
        Process::start(label, Path::new("ip"), &full, log_dir)
    }

    /// Runs `binary args...` on host `name` to its end; returns its standard output.
    pub fn run(&self, name: &str, binary: &Path, args: &[String]) -> String {
        let out = Command::new("ip")
            .args(["netns", "exec", &self.netns(name)])
            .arg(binary)
            .args(args)
            .output()
            .expect("run ip netns exec");
        assert!(
            out.status.success(),
            "{} {args:?} on {name}: {}",
            binary.display(),
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// Quiets a fresh namespace: no IPv6 (no router solicitations, no duplicate-address probes).
    fn quiet(&self, ns: &str) {
        let _ = Command::new("ip")
            .args(["netns", "exec", ns, "sysctl", "-qw", "net.ipv6.conf.all.disable_ipv6=1"])
            .stdout(Stdio::null())
            .status();
        let _ = Command::new("ip")
            .args(["netns", "exec", ns, "sysctl", "-qw", "net.ipv6.conf.default.disable_ipv6=1"])
            .stdout(Stdio::null())
            .status();
    }
}

impl Default for Hosts {
    fn default() -> Self {
        Hosts::new()
    }
}

impl Drop for Hosts {
    fn drop(&mut self) {
        let names: Vec<String> = self.hosts.keys().cloned().collect();
        for name in names {
            let ns = self.netns(&name);
            kill_all_in(&ns);
            let _ = Command::new("ip").args(["netns", "del", &ns]).status();
        }
        kill_all_in(&self.bridge);
        let _ = Command::new("ip").args(["netns", "del", &self.bridge]).status();
    }
}

/// Runs `ip args...`, panicking on failure.
fn ip(args: &[&str]) {
    let out = Command::new("ip").args(args).output().expect("run ip");
    assert!(out.status.success(), "ip {}: {}", args.join(" "), String::from_utf8_lossy(&out.stderr));
}

/// The pids of the processes in namespace `ns`.
pub fn pids_in(ns: &str) -> Vec<u32> {
    let out = Command::new("ip").args(["netns", "pids", ns]).output().expect("run ip netns pids");
    String::from_utf8_lossy(&out.stdout).split_whitespace().filter_map(|p| p.parse().ok()).collect()
}

/// The one process in namespace `ns`, checked to be `binary` itself and a child of this test
/// process (so `ip netns exec` exec'd it: there is no `ip` in between whose memory we would read).
pub fn pid_in(ns: &str, binary: &Path) -> u32 {
    let pids = pids_in(ns);
    assert_eq!(pids.len(), 1, "expected one process in {ns}, found {pids:?}");
    let pid = pids[0];
    let exe = std::fs::read_link(format!("/proc/{pid}/exe")).expect("/proc/PID/exe");
    assert_eq!(exe, binary.canonicalize().expect("binary path"), "pid {pid} in {ns} is not {}", binary.display());
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("/proc/PID/status");
    let parent = status_field(&status, "PPid:").expect("PPid");
    assert_eq!(parent, u64::from(std::process::id()), "pid {pid} in {ns} is not this test's child");
    pid
}

/// Kills (SIGKILL) every process in namespace `ns`: all of them were started by this test.
fn kill_all_in(ns: &str) {
    for pid in pids_in(ns) {
        let _ = Command::new("kill").args(["-KILL", &pid.to_string()]).status();
    }
    // The kernel frees a namespace once its last process is gone; wait for them (a second at most).
    let deadline = Instant::now() + Duration::from_secs(1);
    while !pids_in(ns).is_empty() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Removes the namespaces of earlier runs whose process is gone (a run killed before its cleanup).
fn remove_leftovers() {
    let out = Command::new("ip").args(["netns", "list"]).output().expect("run ip netns list");
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let Some(ns) = line.split_whitespace().next() else { continue };
        let Some(pid) = ns.strip_prefix(PREFIX).and_then(|r| r.split('-').next()) else { continue };
        if pid.parse::<u32>().is_ok() && !Path::new("/proc").join(pid).exists() {
            kill_all_in(ns);
            let _ = Command::new("ip").args(["netns", "del", ns]).status();
        }
    }
}

/// A `Key: value kB`-style field of a `/proc/PID/status` file.
fn status_field(status: &str, key: &str) -> Option<u64> {
    status.lines().find_map(|l| l.strip_prefix(key)).and_then(|v| v.split_whitespace().next()?.parse().ok())
}

/// The TCP sockets listening in namespace `ns` (IPv4; IPv6 is off in the hosts), from its
/// `/proc/net/tcp`.
pub fn listening(ns: &str) -> Vec<(Ipv4Addr, u16)> {
    let out =
        Command::new("ip").args(["netns", "exec", ns, "cat", "/proc/net/tcp"]).output().expect("read /proc/net/tcp");
    let text = String::from_utf8_lossy(&out.stdout);
    text.lines()
        .skip(1)
        .filter_map(|line| {
            let fields: Vec<&str> = line.split_whitespace().collect();
            // sl local_address rem_address st ...; 0A is LISTEN.
            if fields.get(3) != Some(&"0A") {
                return None;
            }
            let (addr, port) = fields.get(1)?.split_once(':')?;
            let addr = Ipv4Addr::from(u32::from_str_radix(addr, 16).ok()?.swap_bytes());
            Some((addr, u16::from_str_radix(port, 16).ok()?))
        })
        .collect()
}

/// A process's resident set size in KiB (`VmRSS`), while it runs.
pub fn rss_kib(pid: u32) -> Option<u64> {
    status_field(&std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?, "VmRSS:")
}

/// A zenoh client configuration connecting only to `endpoint`, scouting off.
pub fn client_config(endpoint: &str) -> String {
    zenoh_config("client", "connect", endpoint)
}

/// A zenohd configuration listening on `endpoint` only, scouting off.
pub fn router_config(endpoint: &str) -> String {
    zenoh_config("router", "listen", endpoint)
}

/// A zenoh configuration of `mode` with `endpoint` as its only `connect` or `listen` endpoint.
fn zenoh_config(mode: &str, role: &str, endpoint: &str) -> String {
    let scouting = "scouting: { multicast: { enabled: false }, gossip: { enabled: false } }";
    format!("{{\n  mode: \"{mode}\",\n  {role}: {{ endpoints: [\"{endpoint}\"] }},\n  {scouting},\n}}\n")
}

/// Writes `text` to `dir/name` and returns the path.
pub fn write_file(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap_or_else(|e| panic!("cannot write {}: {e}", path.display()));
    path
}

/// The global map an observer (`hosts-tool observe`) last wrote to `path`.
pub fn read_map(path: &Path) -> Option<GlobalMap> {
    GlobalMap::decode(std::fs::read(path).ok()?.as_slice()).ok()
}

/// Waits until the observer's map at `path` satisfies `done`; panics with the logs when the
/// keyframes it holds have not grown for `stall` (the station stopped taking them in), or after ten
/// times that in all. A lossy link's backfill is slow and its pace depends on the machine's load:
/// what is checked is that keyframes keep arriving until all are in, not how fast.
pub fn wait_map(
    path: &Path,
    stall: Duration,
    procs: &mut [&mut Process],
    done: impl Fn(&GlobalMap) -> bool,
) -> GlobalMap {
    let started = Instant::now();
    let (mut held, mut grew) = (0u64, started);
    loop {
        let map = read_map(path);
        if let Some(map) = &map {
            if done(map) {
                return map.clone();
            }
            let now: u64 = map.robots.iter().map(|r| r.keyframes).sum();
            if now > held {
                (held, grew) = (now, Instant::now());
            }
        }
        assert!(
            grew.elapsed() < stall && started.elapsed() < 10 * stall,
            "no satisfying global map: its keyframes last grew {:.0} s ago, {:.0} s since the wait began; \
             last seen: {:?}\n{}",
            grew.elapsed().as_secs_f64(),
            started.elapsed().as_secs_f64(),
            map.as_ref().map(describe),
            tails(procs)
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The keyframes robot `robot` has in `map` (0 when it is not there).
pub fn keyframes_of(map: &GlobalMap, robot: u32) -> u64 {
    map.robots.iter().find(|r| r.robot == robot).map_or(0, |r| r.keyframes)
}

/// The `counter packets P bytes B` of each rule of an `nft list` output, in order.
pub fn nft_counters(listing: &str) -> Vec<(u64, u64)> {
    listing
        .lines()
        .filter_map(|line| {
            let rest = &line[line.find("counter packets ")? + "counter packets ".len()..];
            let (packets, rest) = rest.split_once(" bytes ")?;
            let bytes = rest.split_whitespace().next()?;
            Some((packets.parse().ok()?, bytes.parse().ok()?))
        })
        .collect()
}

/// The newest `robot R: S scans, K keyframes (...)` progress line in an edge's log: (S, K).
pub fn edge_progress(log: &str, robot: u32) -> Option<(u64, u64)> {
    edge_reports(log, robot).last().map(|r| (r.scans, r.published))
}

/// One progress line of an edge: what it had done and what it held (`edge::node::Held`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EdgeReport {
    /// Scans registered.
    pub scans: u64,
    /// Keyframes published.
    pub published: u64,
    /// Keyframes made (published or on their way).
    pub made: u64,
    /// Bytes of encoded keyframes held: in the backfill store and on their way to it.
    pub keyframe_bytes: u64,
    /// Bytes the loop closure keeps of the keyframes.
    pub loop_bytes: u64,
}

/// Every progress line of robot `robot` in an edge's log, in order.
pub fn edge_reports(log: &str, robot: u32) -> Vec<EdgeReport> {
    let prefix = format!("robot {robot}: ");
    let number = |s: &str| s.trim().parse::<u64>().ok();
    log.lines()
        .filter_map(|line| {
            let rest = &line[line.find(&prefix)? + prefix.len()..];
            let (scans, rest) = rest.split_once(" scans, ")?;
            let (published, rest) = rest.split_once(" keyframes (")?;
            let (made, rest) = rest.split_once(" keyframes made, holding ")?;
            let (keyframe_bytes, rest) = rest.split_once(" bytes of them")?;
            let (_, rest) = rest.split_once(" and ")?;
            let loop_bytes = rest.strip_suffix(" bytes for loops)")?;
            Some(EdgeReport {
                scans: number(scans)?,
                published: number(published)?,
                made: number(made)?,
                keyframe_bytes: number(keyframe_bytes)?,
                loop_bytes: number(loop_bytes)?,
            })
        })
        .collect()
}

/// One keyframe as a robot's store holds it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Stored {
    /// Sequence number.
    pub seq: u64,
    /// Its encoded message.
    pub bytes: u64,
    /// Points of its cloud.
    pub points: u64,
}

/// Checks that an edge's holdings grew, from `from` to each of `later`, by no more than what the
/// keyframes it made in between explain: their encoded messages (exactly what the store and the
/// channel to it hold of them) and, for the loop closure, their clouds' positions (an upper bound:
/// it keeps them thinned) and a descriptor of `descriptor_bytes` each. `stored` holds every keyframe
/// the edge made, in sequence order. A report that fails says which and by how much.
pub fn growth_explained(
    from: &EdgeReport,
    later: &[EdgeReport],
    stored: &[Stored],
    descriptor_bytes: u64,
) -> Result<(), String> {
    for r in later {
        let made: Vec<&Stored> = stored.iter().filter(|k| (from.made..r.made).contains(&k.seq)).collect();
        if made.len() as u64 != r.made.saturating_sub(from.made) {
            return Err(format!("{r:?}: keyframes {}..{} are not all in the store", from.made, r.made));
        }
        let encoded: u64 = made.iter().map(|k| k.bytes).sum();
        let kept: u64 = made.iter().map(|k| 12 * k.points + descriptor_bytes).sum();
        let grown = r.keyframe_bytes.saturating_sub(from.keyframe_bytes);
        if grown > encoded {
            return Err(format!(
                "{r:?}: holds {grown} more bytes of keyframes than at {from:?}, while the {} made in between \
                 encode to {encoded}",
                made.len()
            ));
        }
        let grown = r.loop_bytes.saturating_sub(from.loop_bytes);
        if grown > kept {
            return Err(format!(
                "{r:?}: the loop closure holds {grown} more bytes than at {from:?}, more than the {kept} of the {} \
                 keyframes made in between",
                made.len()
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Keyframes of 1000 bytes and 400 points; reports after each fifth.
    fn run(keyframe_copies: u64) -> (Vec<EdgeReport>, Vec<Stored>) {
        let stored: Vec<Stored> = (0..20).map(|seq| Stored { seq, bytes: 1000, points: 400 }).collect();
        let reports = (0..=4)
            .map(|i| EdgeReport {
                scans: 50 * i,
                published: 5 * i,
                made: 5 * i,
                keyframe_bytes: keyframe_copies * 5000 * i,
                loop_bytes: 5 * i * (100 * 12 + 64),
            })
            .collect();
        (reports, stored)
    }

    #[test]
    fn an_edge_that_holds_twice_what_it_made_is_caught() {
        let (reports, stored) = run(1);
        assert_eq!(growth_explained(&reports[1], &reports[2..], &stored, 64), Ok(()));
        let (reports, stored) = run(2);
        let err = growth_explained(&reports[1], &reports[2..], &stored, 64).unwrap_err();
        assert!(err.contains("holds 10000 more bytes of keyframes") && err.contains("encode to 5000"), "{err}");
        // Keyframes the store does not hold cannot explain anything.
        let (reports, mut stored) = run(1);
        stored.retain(|k| k.seq != 12);
        assert!(growth_explained(&reports[1], &reports[2..], &stored, 64).is_err());
    }

    #[test]
    fn progress_lines_are_read_as_the_edge_writes_them() {
        let held = edge::node::Held { made: 27, store: 1000, in_flight: 234, loops: 5678 };
        let log = format!(
            "2026-01-01T00:00:00Z  INFO edge::node: robot 3: 200 scans, 25 keyframes ({held})\n\
             robot 3: source done after 200 scans\nrobot 4: 1 scans, 0 keyframes ({held})\n"
        );
        let expected = EdgeReport { scans: 200, published: 25, made: 27, keyframe_bytes: 1234, loop_bytes: 5678 };
        assert_eq!(edge_reports(&log, 3), vec![expected]);
        assert_eq!(edge_progress(&log, 3), Some((200, 25)));
    }
}
