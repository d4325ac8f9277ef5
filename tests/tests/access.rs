//! Only the fleet gets in: the real `zenohd` router on loopback with the configuration
//! `emr-station certs` writes (TLS with client certificates required, access control by
//! certificate name), the real station and edges as its members.
//!
//! Refused: a peer without a certificate, a certificate of another CA, an expired certificate of
//! the fleet's CA; robot 3's certificate publishing as robot 4; a tool on plain TCP publishing.
//! Let in: robot 3 as robot 3 (its keyframes reach the station), a tool on plain TCP reading the
//! global map.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use prost::Message;
use proto::{Fleet, Keyframe};
use station::access::Member;
use station::access::certs::{Authority, Validity};
use station::access::zenoh_config::{self, CertFiles};
use tests::*;

const FLEET: &str = "locked";
/// Four robots: robot 3 drives as itself, robot 4 with robot 3's certificate.
const SCENARIO: &str = "campus";
const FRAMES: usize = 150;
const TIMEOUT: Duration = Duration::from_secs(300);

/// A router with the fleet's configuration, listening on loopback only.
struct Router {
    process: Process,
    tls: String,
    tools_port: u16,
    certs: PathBuf,
}

impl Router {
    fn start(dir: &Path) -> Router {
        let (tls_port, tools_port) = (bus::free_port().unwrap(), bus::free_port().unwrap());
        let tls = format!("tls/127.0.0.1:{tls_port}");
        let certs = dir.join("fleet");
        let status = std::process::Command::new(binary("emr-station"))
            .args(["certs", "--fleet", FLEET, "--robots", "3,4", "--days", "2"])
            .arg("--out")
            .arg(&certs)
            .args(["--router-listen", &tls, "--router-listen", &bus::endpoint(tools_port), "--router-connect", &tls])
            .status()
            .expect("run emr-station certs");
        assert!(status.success(), "emr-station certs failed");
        let args = vec!["-c".to_owned(), certs.join("router.json5").display().to_string()];
        let process = Process::start("router", &zenohd(), &args, dir);
        Router { process, tls, tools_port, certs }
    }

    /// A member's zenoh configuration file, as `certs` wrote it.
    fn config(&self, member: Member) -> PathBuf {
        self.certs.join(format!("{}.json5", member.file_stem()))
    }

    /// Opens a client session with `files`' certificate of `member` (or none).
    fn open(&self, member: Option<Member>, files: &CertFiles) -> Result<zenoh::Session, String> {
        let mut config =
            zenoh_config::member(member.unwrap_or(Member::Station), std::slice::from_ref(&self.tls), files);
        if member.is_none() {
            let tls = config["transport"]["link"]["tls"].as_object_mut().unwrap();
            tls.remove("connect_certificate");
            tls.remove("connect_private_key");
            // A plain TLS client: it checks the router, the router finds no certificate to check.
            tls.insert("enable_mtls".into(), false.into());
        }
        let config = zenoh::Config::from_json5(&config.to_string()).expect("client config");
        let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        runtime.block_on(async { zenoh::open(config).await }).map_err(|e| e.to_string())
    }
}

fn station(router: &Router, dir: &Path) -> Process {
    let mut args = station_args(FLEET, 0, &dir.join("station-data"));
    args.truncate(args.len() - 2);
    args.extend(["--zenoh".into(), router.config(Member::Station).display().to_string()]);
    Process::start("station", &binary("emr-station"), &args, dir)
}

/// An edge replaying simulated robot `robot`, with `member`'s certificate.
fn edge(router: &Router, member: Member, robot: u32, dir: &Path) -> Process {
    let mut args = edge_args(FLEET, SCENARIO, robot, FRAMES, 0, &summary(dir, robot));
    args.truncate(args.len() - 2);
    args.extend(["--zenoh".into(), router.config(member).display().to_string()]);
    Process::start(&format!("edge{robot}-as-{member}"), &binary("emr-edge"), &args, dir)
}

fn summary(dir: &Path, robot: u32) -> PathBuf {
    dir.join(format!("edge{robot}-summary.json"))
}

/// Certificates another way: `member`'s identity from `ca`, beside the fleet's CA certificate.
fn identity_dir(dir: &Path, name: &str, fleet_ca: &Path, ca: &Authority, member: Member, valid: Validity) -> CertFiles {
    let files = CertFiles { dir: dir.join(name) };
    std::fs::create_dir_all(&files.dir).unwrap();
    std::fs::copy(fleet_ca, files.ca()).unwrap();
    let id = ca.issue(&Fleet::new(FLEET).unwrap(), member, &[], valid).unwrap();
    std::fs::write(files.certificate(member), id.certificate_pem).unwrap();
    std::fs::write(files.key(member), id.key_pem).unwrap();
    files
}

#[test]
fn only_the_fleets_certificates_get_in_and_each_speaks_only_for_itself() {
    let dir = scratch();
    let mut router = Router::start(dir.path());
    let observer = wait_for_router(&mut router);
    let fleet_files = CertFiles { dir: router.certs.clone() };

    // Refused at the door.
    let fleet = Fleet::new(FLEET).unwrap();
    let foreign = Authority::new(&fleet, Validity::days_from_now(2)).unwrap();
    let foreign_files =
        identity_dir(dir.path(), "foreign", &fleet_files.ca(), &foreign, Member::Robot(3), Validity::days_from_now(2));
    let fleet_ca = Authority::from_pem(
        &std::fs::read_to_string(fleet_files.ca()).unwrap(),
        &std::fs::read_to_string(router.certs.join("ca.key")).unwrap(),
    )
    .unwrap();
    let yesterday = Validity::days_from_now(0);
    let expired =
        Validity { not_before: yesterday.not_before - time::Duration::days(2), not_after: yesterday.not_before };
    let expired_files = identity_dir(dir.path(), "expired", &fleet_files.ca(), &fleet_ca, Member::Robot(3), expired);
    for (what, member, files) in [
        ("no certificate", None, &fleet_files),
        ("another CA's certificate", Some(Member::Robot(3)), &foreign_files),
        ("an expired certificate", Some(Member::Robot(3)), &expired_files),
    ] {
        let opened = router.open(member, files);
        assert!(opened.is_err(), "a peer with {what} was let in");
        println!("{what}: refused ({})", opened.err().unwrap_or_default().lines().next().unwrap_or_default());
    }
    // The control: the fleet's own certificate opens the same door.
    router.open(Some(Member::Robot(3)), &fleet_files).expect("robot 3's own certificate is let in");

    // Inside: robot 3 as itself, and with the same certificate as robot 4; a tool that publishes.
    let mut station = station(&router, dir.path());
    let mut honest = edge(&router, Member::Robot(3), 3, dir.path());
    let mut impostor = edge(&router, Member::Robot(3), 4, dir.path());
    let forged = Keyframe { robot: 5, seq: 0, ..Default::default() }.encode_to_vec();
    let tool_put =
        observer.runtime.block_on(async { observer.session.put("emr/locked/robot/5/keyframe", forged).await });
    let procs = &mut [&mut router.process, &mut station, &mut honest, &mut impostor];
    let made = wait_summary(&summary(dir.path(), 3), TIMEOUT, procs).keyframes;
    let forged = wait_summary(&summary(dir.path(), 4), TIMEOUT, procs).keyframes;
    assert!(forged > 0, "the impostor made no keyframes to send");
    let map = observer.wait_global_map(TIMEOUT, procs, |m| holds_all(m, &[(3, made)]));
    // The impostor finished at the same time as the honest robot; give its keyframes time to arrive.
    std::thread::sleep(Duration::from_secs(3));
    let status = observer.next_status(Duration::from_secs(5)).expect("station status over plain TCP");
    println!(
        "tool's put: {tool_put:?}; station: robots {:?}, {} keyframes; {}",
        status.robots,
        status.keyframes,
        describe(&map)
    );
    assert_eq!(status.robots, vec![3], "the station heard from robots other than 3\n{}", tails(procs));
    assert_eq!(status.keyframes, made, "keyframes held besides robot 3's {made}\n{}", tails(procs));

    // The control: robot 4 with its own certificate is heard.
    drop(impostor);
    std::fs::remove_file(summary(dir.path(), 4)).unwrap();
    let mut robot4 = edge(&router, Member::Robot(4), 4, dir.path());
    let procs = &mut [&mut router.process, &mut station, &mut robot4];
    let own = wait_summary(&summary(dir.path(), 4), TIMEOUT, procs).keyframes;
    assert_eq!(own, forged, "robot 4 made different keyframes with its own certificate");
    observer.wait_global_map(TIMEOUT, procs, |m| holds_all(m, &[(3, made), (4, own)]));
}

/// An observer on the router's plain-TCP tool port, once the router listens.
fn wait_for_router(router: &mut Router) -> Observer {
    let deadline = Instant::now() + Duration::from_secs(30);
    while std::net::TcpStream::connect(("127.0.0.1", router.tools_port)).is_err() {
        assert!(router.process.running(), "zenohd stopped\n{}", router.process.tail());
        assert!(Instant::now() < deadline, "zenohd did not open its ports\n{}", router.process.tail());
        std::thread::sleep(Duration::from_millis(200));
    }
    Observer::connect(FLEET, router.tools_port)
}
