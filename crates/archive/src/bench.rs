//! `tagdeflect archive-bench`: how many feed lines per second one archive ingests.
//!
//! Several simulated rigs (one MQTT client each) publish synthetic feed lines shaped like a
//! 3-camera rig's (camera health for 3 cameras, `--tags` solved tags with σ, two gauges,
//! load and stroke) as fast as the broker takes them, at QoS 1; one archive (in this
//! process, the same code as `tagdeflect archive`) writes them into PostgreSQL. The figure
//! is lines committed per second from the first publish to the last commit. Without
//! `--mqtt` / `--postgres` a local Mosquitto and a local PostgreSQL cluster (durable:
//! fsync on) are started in a temporary folder and removed afterwards.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use rumqttc::{AsyncClient, QoS};
use tokio::sync::watch;

use crate::service::{run_until, ArchiveStats};
use crate::{ArchiveError, ArchiveOptions};
use tagdeflect_core::feed::{CameraHealth, FeedLine, FeedTag};

/// Options of `tagdeflect archive-bench`.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct ArchiveBenchOptions {
    /// Simulated rigs publishing at once.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 4))]
    pub rigs: usize,
    /// Feed lines each rig publishes.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 3000))]
    pub lines: usize,
    /// Solved tags per feed line.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 8))]
    pub tags: usize,
    /// Feed lines per transaction at most.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1000))]
    pub batch: usize,
    /// Use this broker instead of a local Mosquitto.
    #[cfg_attr(feature = "clap", arg(long))]
    pub mqtt: Option<String>,
    /// Use this database instead of a local PostgreSQL cluster (tables are added to it).
    #[cfg_attr(feature = "clap", arg(long))]
    pub postgres: Option<String>,
}

/// A synthetic feed line of a 3-camera rig, as JSON.
fn synthetic_line(seq: u64, t_ns: i64, tags: usize) -> String {
    let tags: Vec<FeedTag> = (0..tags as u32)
        .map(|id| FeedTag {
            id,
            pos_mm: [100.0 * id as f64 + 0.12345, 20.5 + 1e-3 * seq as f64, 300.25 - 1e-3 * seq as f64],
            disp_mm: [0.00123, 1e-3 * seq as f64, -1e-3 * seq as f64],
            views: 3,
            sigma_mm: Some([0.0021, 0.0019, 0.0042]),
            disp_sigma_mm: None,
            reproj_px: Some(0.081),
        })
        .collect();
    let cameras = ["left", "centre", "right"]
        .iter()
        .map(|n| CameraHealth {
            name: n.to_string(),
            frame: true,
            background_tags: 4,
            specimen_tags: tags.len(),
            pose_reproj_px: Some(0.12),
            posed: true,
            ..CameraHealth::default()
        })
        .collect();
    let line = FeedLine {
        seq,
        t_ns,
        load_kn: Some(12.5 + 1e-3 * seq as f64),
        stroke_mm: Some(1e-3 * seq as f64),
        tags,
        net_deflection_mm: Some(1e-3 * seq as f64),
        reproj_px: Some(0.08),
        cameras,
        utm: Some("ok".into()),
        dropped_sets: Some(0),
        latency_ms: Some(21.4),
        mqtt_dropped: Some(0),
        ..FeedLine::default()
    };
    let mut v = serde_json::to_value(&line).expect("line serialises");
    v["gauges"] = serde_json::json!({
        "cmod": {"value": 0.213, "sigma": 0.004, "unit": "mm"},
        "rotation": {"value": 0.0012, "sigma": 0.0001, "unit": "rad"},
    });
    v.to_string()
}

/// Polls a client's connection for as long as the benchmark runs: an error (the broker
/// refused or dropped the connection) is logged and the next poll reconnects — a poller that
/// stopped at the first error would leave its publisher waiting forever for room to send.
async fn drive(el: &mut rumqttc::EventLoop, who: &str) {
    loop {
        if let Err(e) = el.poll().await {
            tracing::warn!("archive-bench: the {who}'s connection: {e}; reconnecting");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
}

/// Runs the benchmark and prints the figures.
pub fn run(opts: &ArchiveBenchOptions) -> Result<(), ArchiveError> {
    let local_mqtt = match opts.mqtt {
        None => Some(crate::local::LocalMosquitto::start().map_err(|cause| ArchiveError::LocalServer { server: "Mosquitto", cause })?),
        Some(_) => None,
    };
    let local_pg = match opts.postgres {
        None => Some(crate::local::LocalPostgres::start(true).map_err(|cause| ArchiveError::LocalServer { server: "PostgreSQL", cause })?),
        Some(_) => None,
    };
    let mqtt = opts.mqtt.clone().or_else(|| local_mqtt.as_ref().map(|m| m.url())).expect("a broker");
    let postgres = opts.postgres.clone().or_else(|| local_pg.as_ref().map(|p| p.url())).expect("a database");
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().map_err(ArchiveError::Runtime)?;
    let res = rt.block_on(bench(opts, mqtt, postgres));
    drop(rt);
    drop(local_mqtt);
    drop(local_pg);
    res
}

async fn bench(opts: &ArchiveBenchOptions, mqtt: String, postgres: String) -> Result<(), ArchiveError> {
    let run_id = format!("{:08x}", rand::random::<u32>());
    let archive_opts = ArchiveOptions {
        command: None,
        mqtt: Some(mqtt.clone()),
        postgres: Some(postgres),
        topic: "tagdeflect/{rig}/{test}".into(),
        group: None,
        client_id: Some(format!("tagdeflect-archive-bench-{run_id}")),
        ca_file: None,
        batch: opts.batch,
    };
    let stats = Arc::new(ArchiveStats::default());
    let (stop_tx, stop_rx) = watch::channel(false);
    let archive = tokio::spawn(run_until(archive_opts, stats.clone(), stop_rx));

    // One line first: the archive is subscribed and the schema in place once it is stored.
    let (probe, mut probe_loop) = AsyncClient::new(
        tagdeflect_wire::mqtt_options(&mqtt, &format!("bench-probe-{run_id}"), None, None, None)
            .map_err(|m| ArchiveError::BadOption(m.to_string()))?,
        16,
    );
    let probe_task = tokio::spawn(async move { drive(&mut probe_loop, "probe").await });
    let until = Instant::now() + Duration::from_secs(30);
    let mut k = 0;
    while stats.inserted.load(Ordering::Relaxed) == 0 {
        if Instant::now() >= until {
            return Err(ArchiveError::Bench(format!("the archive stored nothing within 30 s (broker {mqtt})")));
        }
        // Bounded: a connection that takes nothing must end in the error above, not a hang.
        let publish =
            probe.publish(format!("tagdeflect/bench-probe/{run_id}/feed"), QoS::AtLeastOnce, false, synthetic_line(k, 0, opts.tags));
        if let Ok(r) = tokio::time::timeout(Duration::from_secs(1), publish).await {
            r?;
        }
        k += 1;
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    probe_task.abort();
    let base = stats.inserted.load(Ordering::Relaxed);
    let size = synthetic_line(0, 0, opts.tags).len();

    let total = (opts.rigs * opts.lines) as u64;
    let t0 = Instant::now();
    let mut publishers = Vec::new();
    for r in 0..opts.rigs {
        let mut mo = tagdeflect_wire::mqtt_options(&mqtt, &format!("bench-rig-{r}-{run_id}"), None, None, None)
            .map_err(|m| ArchiveError::BadOption(m.to_string()))?;
        mo.set_inflight(100);
        let (client, mut el) = AsyncClient::new(mo, 64);
        let driver = tokio::spawn(async move { drive(&mut el, "rig").await });
        let (lines, tags, run_id) = (opts.lines, opts.tags, run_id.clone());
        publishers.push(tokio::spawn(async move {
            let topic = format!("tagdeflect/bench-rig-{r}/{run_id}/feed");
            let t_start = tagdeflect_core::clock::now_epoch_ns();
            for seq in 0..lines as u64 {
                let line = synthetic_line(seq, t_start + seq as i64 * 33_333_333, tags);
                if client.publish(topic.clone(), QoS::AtLeastOnce, false, line).await.is_err() {
                    break;
                }
            }
            (client, driver)
        }));
    }
    let mut clients = Vec::new();
    let until = tokio::time::Instant::now() + Duration::from_secs(300);
    for p in publishers {
        match tokio::time::timeout_at(until, p).await {
            Ok(c) => clients.push(c?),
            Err(_) => return Err(ArchiveError::Bench("the simulated rigs could not publish their lines within 300 s".into())),
        }
    }
    let published_s = t0.elapsed().as_secs_f64();
    let until = Instant::now() + Duration::from_secs(300);
    while stats.inserted.load(Ordering::Relaxed) - base < total {
        if Instant::now() >= until {
            return Err(ArchiveError::Bench(format!(
                "only {} of {total} lines stored after 300 s",
                stats.inserted.load(Ordering::Relaxed) - base
            )));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let secs = t0.elapsed().as_secs_f64();
    let _ = stop_tx.send(true);
    let _ = tokio::time::timeout(Duration::from_secs(10), archive).await;
    for (_, d) in clients {
        d.abort();
    }
    let rate = total as f64 / secs;
    let batches = stats.batches.load(Ordering::Relaxed).max(1);
    println!("archive-bench: {} rigs x {} feed lines ({} tags, {} bytes a line) at QoS 1", opts.rigs, opts.lines, opts.tags, size);
    println!("archive-bench: published in {published_s:.2} s; all {total} lines committed after {secs:.2} s");
    println!(
        "archive-bench: one archive ingests {rate:.0} feed lines/s ({:.0} lines a transaction on average, {} duplicates)",
        (stats.inserted.load(Ordering::Relaxed) as f64) / batches as f64,
        stats.duplicates.load(Ordering::Relaxed)
    );
    println!(
        "archive-bench: a rig with 3 cameras at 30 frame sets/s sends 30 lines/s: this archive keeps up with about {:.0} such rigs",
        rate / 30.0
    );
    Ok(())
}
