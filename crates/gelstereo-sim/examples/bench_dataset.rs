//! Throughput of dataset generation, the figure quoted in README and docs/sim.md.
//!
//! ```text
//! cargo run --release -p gelstereo-sim --example bench_dataset -- [EXPERIMENTS] [FRAMES] [RANDOMIZATION]
//! ```
//! Defaults 20 x 50 = 1,000 stereo frames, `full` randomisation, written (PNG) to a temporary folder
//! that is deleted afterwards. Prints wall-clock frames/s, the process's CPU time per frame (user +
//! system, from /proc/self/stat) and the load average, so that a figure measured on a busy machine
//! can be extrapolated honestly: on N idle cores, frames/s ~= N / (CPU s per frame) since frames are
//! independent (rayon).

use std::time::Instant;

use gelstereo_sim::dataset::{DatasetConfig, Randomization, write_dataset};

fn cpu_seconds() -> f64 {
    // Fields 14 and 15 of /proc/self/stat: utime and stime in clock ticks (100 per second on Linux).
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit_once(')').map(|(_, rest)| rest).unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let experiments: u32 = args.first().map(|s| s.parse()).transpose()?.unwrap_or(20);
    let frames: u32 = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(50);
    let randomization: Randomization = args
        .get(2)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(Randomization::Full);
    let mut config = DatasetConfig::new(experiments, frames, 1);
    config.randomization = randomization;
    let dir = std::env::temp_dir().join(format!("gelstereo-bench-{}", std::process::id()));
    let out = dir.join("data");
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let cpu0 = cpu_seconds();
    let t = Instant::now();
    let summary = write_dataset(&out, &config, false, &|| {})?;
    let wall = t.elapsed().as_secs_f64();
    let cpu = cpu_seconds() - cpu0;
    let bytes: u64 = walk(&out);
    let _ = std::fs::remove_dir_all(&dir);
    let n = summary.frames as f64;
    let threads = rayon::current_num_threads();
    println!(
        "{} stereo frames ({randomization:?}) in {wall:.1} s wall = {:.1} stereo frames/s on {threads} threads; \
         CPU {:.1} ms per stereo frame (-> {:.0} frames/s on 2 idle cores); {:.0} kB per stereo frame; \
         load average before: {}",
        summary.frames,
        n / wall,
        1e3 * cpu / n,
        2.0 * n / cpu,
        bytes as f64 / n / 1e3,
        load.split_whitespace().take(3).collect::<Vec<_>>().join(" ")
    );
    Ok(())
}

fn walk(dir: &std::path::Path) -> u64 {
    let Ok(rd) = std::fs::read_dir(dir) else { return 0 };
    rd.filter_map(Result::ok)
        .map(|e| {
            let p = e.path();
            if p.is_dir() {
                walk(&p)
            } else {
                e.metadata().map(|m| m.len()).unwrap_or(0)
            }
        })
        .sum()
}
