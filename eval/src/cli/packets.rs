//! `emr-eval packets`: how fast the packet decoders run, against the time the sensor took to send.

use std::fmt;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use cloud::stopwatch::Stopwatch;
use edge::recording::capture::{Capture, Datagram};
use edge::recording::{PacketDecoder, PacketOptions, assembler_for};

use super::median;

/// Decoding figures of one capture.
pub struct CaptureFigures {
    /// File name.
    pub name: String,
    /// Datagrams in the capture.
    pub datagrams: usize,
    /// Rotations decoded (partial ones included).
    pub rotations: usize,
    /// Points decoded over all rotations.
    pub points: usize,
    /// Seconds from the first datagram to the last, as captured.
    pub sensor_s: f64,
    /// Median seconds to decode the whole capture on one core.
    pub decode_s: f64,
}

impl CaptureFigures {
    /// How many times faster than the sensor sent it.
    pub fn real_time_factor(&self) -> f64 {
        self.sensor_s / self.decode_s
    }
}

/// Figures of every capture of a directory.
pub struct PacketsReport {
    /// Timed passes per capture (the median is reported).
    pub repeat: usize,
    /// One row per capture, in name order.
    pub captures: Vec<CaptureFigures>,
}

/// Decodes every `.pcap` / `.pcapng` of `dir` `repeat` times, from memory.
pub fn packets(dir: &Path, repeat: usize) -> Result<PacketsReport> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot list {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "pcap" || e == "pcapng"))
        .collect();
    files.sort();
    if files.is_empty() {
        bail!("{}: no .pcap or .pcapng captures", dir.display());
    }
    let captures = files.iter().map(|f| figures(f, repeat.max(1))).collect::<Result<_>>()?;
    Ok(PacketsReport { repeat, captures })
}

fn figures(path: &Path, repeat: usize) -> Result<CaptureFigures> {
    let datagrams: Vec<Datagram> = Capture::open(path)
        .with_context(|| format!("cannot open {}", path.display()))?
        .collect::<Result<_, _>>()
        .with_context(|| format!("cannot read {}", path.display()))?;
    let (first, last) = match (datagrams.first(), datagrams.last()) {
        (Some(f), Some(l)) => (f.received, l.received),
        _ => bail!("{}: no UDP datagrams", path.display()),
    };
    let mut times = Vec::with_capacity(repeat);
    let (mut rotations, mut points) = (0, 0);
    // A stream's steady state: the caller gives each rotation's returns back once it made its
    // cloud, so a pass decodes into the memory of the pass before, as a live source does.
    let mut spare = Vec::new();
    for _ in 0..repeat {
        let mut decoder = PacketDecoder::new(assembler_for(Some(path), &PacketOptions::default())?, None);
        decoder.recycle(std::mem::take(&mut spare));
        let watch = Stopwatch::start();
        let mut decoded: Vec<usize> = Vec::new();
        for d in &datagrams {
            if let Some(rotation) = decoder.push(d.destination_port, &d.payload, d.received) {
                decoded.push(rotation.returns.len());
                decoder.recycle(rotation.returns);
            }
        }
        if let Some(rotation) = decoder.finish() {
            decoded.push(rotation.returns.len());
            spare = rotation.returns;
        }
        times.push(watch.elapsed_ms() / 1e3);
        (rotations, points) = (decoded.len(), decoded.iter().sum());
    }
    Ok(CaptureFigures {
        name: path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
        datagrams: datagrams.len(),
        rotations,
        points,
        sensor_s: last - first,
        decode_s: median(&times),
    })
}

impl fmt::Display for PacketsReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "| capture | datagrams | rotations | points | sent in | decoded in (median of {}) | x real time |",
            self.repeat
        )?;
        writeln!(f, "|---|---|---|---|---|---|---|")?;
        for c in &self.captures {
            writeln!(
                f,
                "| {} | {} | {} | {} | {:.1} ms | {:.2} ms | {:.0} |",
                c.name,
                c.datagrams,
                c.rotations,
                c.points,
                c.sensor_s * 1e3,
                c.decode_s * 1e3,
                c.real_time_factor()
            )?;
        }
        Ok(())
    }
}
