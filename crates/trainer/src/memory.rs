//! This process's memory high-water mark, for run records and sweep tables.

/// Peak resident set size of this process in MiB (`VmHWM` of `/proc/self/status`);
/// `None` where the platform does not report it.
pub fn peak_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

#[cfg(test)]
mod tests {
    #[test]
    #[cfg(target_os = "linux")]
    fn peak_rss_grows_with_a_touched_allocation() {
        let before = super::peak_rss_mb().expect("linux reports VmHWM");
        let big = vec![1u8; 64 << 20];
        let after = super::peak_rss_mb().expect("linux reports VmHWM");
        assert!(big.iter().map(|&b| b as usize).sum::<usize>() == 64 << 20);
        assert!(after >= before + 60.0, "{before} MiB → {after} MiB");
    }
}
