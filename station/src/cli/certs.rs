//! `emr-station certs`: a fleet's certificates and the zenoh configurations that use them.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use proto::Fleet;
use station::access::Member;
use station::access::certs::{Authority, Identity, Validity, default_router_hosts};
use station::access::zenoh_config::{self, CertFiles};

// `emr-station certs`.
#[derive(Args, Debug)]
pub struct CertsArgs {
    /// Fleet name.
    #[arg(long)]
    fleet: String,
    /// The robots' ids, comma-separated (e.g. 1,2,3). Run again with more to add robots: the CA
    /// and the certificates already in OUT are kept.
    #[arg(long, value_delimiter = ',', required = true)]
    robots: Vec<u32>,
    /// Directory to write into (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Days the new certificates are valid.
    #[arg(long, default_value_t = 365)]
    days: u32,
    /// A name members dial the router by, written into its certificate (repeatable; default:
    /// router, localhost, 127.0.0.1).
    #[arg(long = "router-host", value_name = "NAME")]
    router_hosts: Vec<String>,
    /// Where the router listens (repeatable): `tls/...` endpoints for the members, `tcp/...` ones
    /// for read-only tools (keep those on a loopback or host-only address).
    #[arg(long = "router-listen", value_name = "ENDPOINT", default_values_t = [String::from("tls/0.0.0.0:7448"), String::from("tcp/0.0.0.0:7447")])]
    router_listen: Vec<String>,
    /// The router's endpoint the members dial (repeatable).
    #[arg(long = "router-connect", value_name = "ENDPOINT", default_values_t = [String::from("tls/router:7448")])]
    router_connect: Vec<String>,
    /// Where the processes will find OUT's files (e.g. where a container mounts it); default: OUT.
    #[arg(long, value_name = "DIR")]
    files_at: Option<PathBuf>,
    /// Issue new certificates even for members that have one in OUT (the CA is still kept).
    #[arg(long)]
    renew: bool,
}

pub fn certs(args: CertsArgs) -> Result<()> {
    let fleet = Fleet::new(&args.fleet).with_context(|| format!("fleet {:?}", args.fleet))?;
    if let Some(e) = args.router_listen.iter().chain(&args.router_connect).find(|e| !is_tls_or_tcp(e)) {
        bail!("endpoint {e:?}: the router's endpoints are tls/HOST:PORT or tcp/HOST:PORT");
    }
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let validity = Validity::days_from_now(args.days);
    let ca = load_or_make_ca(&fleet, &args.out, validity)?;
    let hosts = if args.router_hosts.is_empty() { default_router_hosts() } else { args.router_hosts.clone() };
    let files_at = match &args.files_at {
        Some(dir) => dir.clone(),
        None => std::path::absolute(&args.out).with_context(|| format!("resolving {}", args.out.display()))?,
    };
    let files = CertFiles { dir: files_at };

    let members = [Member::Router, Member::Station].into_iter().chain(args.robots.iter().map(|&r| Member::Robot(r)));
    for member in members {
        let held = args.out.join(format!("{}.pem", member.file_stem())).exists();
        if held && !args.renew {
            println!("kept   {member}");
        } else {
            let identity = ca.issue(&fleet, member, &hosts, validity)?;
            write_identity(&args.out, member, &identity)?;
            println!("issued {member} ({}, valid {} days)", identity.common_name, args.days);
        }
        let config = match member {
            Member::Router => {
                let (tls, tcp): (Vec<String>, Vec<String>) =
                    args.router_listen.iter().cloned().partition(|e| e.starts_with("tls/"));
                zenoh_config::router(&fleet, &args.robots, &tls, &tcp, &files)
            }
            _ => zenoh_config::member(member, &args.router_connect, &files),
        };
        let path = args.out.join(format!("{}.json5", member.file_stem()));
        write(&path, &serde_json::to_string_pretty(&config)?, 0o644)?;
    }
    println!(
        "wrote {}: ca.pem (give to every member), ca.key (keep it off the robots), per member its .pem, .key and .json5",
        args.out.display()
    );
    Ok(())
}

fn is_tls_or_tcp(e: &str) -> bool {
    e.strip_prefix("tls/").or_else(|| e.strip_prefix("tcp/")).is_some_and(|a| a.contains(':'))
}

/// The CA in `dir` if there is one, else a new one written there.
fn load_or_make_ca(fleet: &Fleet, dir: &Path, validity: Validity) -> Result<Authority> {
    let (cert, key) = (dir.join("ca.pem"), dir.join("ca.key"));
    if cert.exists() || key.exists() {
        let read =
            |p: &Path| std::fs::read_to_string(p).with_context(|| format!("reading the fleet CA {}", p.display()));
        let ca =
            Authority::from_pem(&read(&cert)?, &read(&key)?).with_context(|| format!("the CA in {}", dir.display()))?;
        println!("kept   the CA in {}", dir.display());
        return Ok(ca);
    }
    let ca = Authority::new(fleet, validity)?;
    write(&key, ca.key_pem(), 0o600)?;
    write(&cert, ca.certificate_pem(), 0o644)?;
    println!("issued the CA (emr-{}-ca)", fleet.as_str());
    Ok(ca)
}

fn write_identity(dir: &Path, member: Member, identity: &Identity) -> Result<()> {
    write(&dir.join(format!("{}.key", member.file_stem())), &identity.key_pem, 0o600)?;
    write(&dir.join(format!("{}.pem", member.file_stem())), &identity.certificate_pem, 0o644)
}

/// Writes `text` with `mode` (keys are readable by their owner only).
fn write(path: &Path, text: &str, mode: u32) -> Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let _ = std::fs::remove_file(path);
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(mode)
        .open(path)
        .with_context(|| format!("writing {}", path.display()))?;
    file.write_all(text.as_bytes()).with_context(|| format!("writing {}", path.display()))
}
