//! Peak GPU memory of a piece of work, read from `nvidia-smi` while it runs.
//! Both sides of `bench model` are measured this way (the same libtorch
//! caching allocator on each), so the figures compare; the process's CUDA
//! context is included in both.

use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// The tool that reports the GPU's used memory.
pub const NVIDIA_SMI: &str = "nvidia-smi";

/// Used memory of GPU `gpu` in MiB, from `nvidia-smi --query-gpu=memory.used`;
/// `None` when the tool is missing or prints something else.
fn gpu_used_mib(program: &str, gpu: usize) -> Option<u64> {
    let out = Command::new(program)
        .args([
            "--query-gpu=memory.used",
            "--format=csv,noheader,nounits",
            "-i",
            &gpu.to_string(),
        ])
        .output()
        .ok()?;
    if !out.status.success() {
        return None;
    }
    parse_used_mib(&String::from_utf8_lossy(&out.stdout))
}

/// The first line of `nvidia-smi --format=csv,noheader,nounits` as MiB.
fn parse_used_mib(text: &str) -> Option<u64> {
    text.lines().next()?.trim().parse().ok()
}

/// Runs `f` while a thread polls the used memory of `gpu` every 20 ms with
/// `program` (normally [`NVIDIA_SMI`]); returns `f`'s result and the peak
/// above the memory used before it started (`None` on CPU, or when the GPU
/// cannot be queried).
pub fn with_gpu_peak<T, E>(
    program: &str,
    gpu: Option<usize>,
    f: impl FnOnce() -> Result<T, E>,
) -> Result<(T, Option<u64>), E> {
    let Some(gpu) = gpu else {
        return Ok((f()?, None));
    };
    let Some(idle) = gpu_used_mib(program, gpu) else {
        return Ok((f()?, None));
    };
    let stop = Arc::new(AtomicBool::new(false));
    let poller = {
        let (stop, program) = (Arc::clone(&stop), program.to_owned());
        std::thread::spawn(move || {
            let mut peak = idle;
            loop {
                if let Some(m) = gpu_used_mib(&program, gpu) {
                    peak = peak.max(m);
                }
                if stop.load(Ordering::Relaxed) {
                    return peak;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        })
    };
    let result = f();
    stop.store(true, Ordering::Relaxed);
    let peak = poller.join().ok();
    Ok((result?, peak.map(|p| p.saturating_sub(idle))))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_nvidia_smi_memory_lines() {
        assert_eq!(parse_used_mib("81234\n"), Some(81234));
        assert_eq!(parse_used_mib(" 17 \n4\n"), Some(17));
        assert_eq!(parse_used_mib("[N/A]\n"), None);
        assert_eq!(parse_used_mib(""), None);
    }

    #[test]
    fn peak_probe_reports_the_rise_above_idle_and_passes_errors_on() {
        // A stand-in for nvidia-smi whose reading rises by 100 MiB per call.
        let dir = tempfile::tempdir().expect("tempdir");
        let counter = dir.path().join("n");
        let fake = dir.path().join("fake-smi");
        std::fs::write(
            &fake,
            format!(
                "#!/bin/sh\nn=$(cat {c} 2>/dev/null || echo 0)\necho $((n + 1)) > {c}\necho $((1000 + 100 * n))\n",
                c = counter.display()
            ),
        )
        .expect("write");
        let status = Command::new("chmod").arg("+x").arg(&fake).status();
        assert!(status.is_ok_and(|s| s.success()));
        let prog = fake.to_str().expect("utf-8 path");
        let (v, peak) = with_gpu_peak(prog, Some(0), || {
            std::thread::sleep(Duration::from_millis(200));
            Ok::<_, String>(7)
        })
        .expect("probe");
        assert_eq!(v, 7);
        let peak = peak.expect("a peak");
        assert!(peak >= 100, "peak {peak}: the readings rose above idle");
        // CPU: no probe; a missing tool: no figure, the closure still runs.
        let cpu = with_gpu_peak(prog, None, || Ok::<_, String>(1));
        assert_eq!(cpu.expect("cpu").1, None);
        let missing = dir.path().join("absent");
        let r = with_gpu_peak(missing.to_str().expect("utf-8"), Some(0), || {
            Ok::<_, String>(2)
        });
        assert_eq!(r.expect("missing tool").1, None);
        // The closure's error comes back (and the poller is stopped).
        let e = with_gpu_peak(prog, Some(0), || Err::<(), _>("boom".to_owned()));
        assert_eq!(e, Err("boom".to_owned()));
    }
}
