//! What Linux says about memory: how much the system can still give, and this process's peak.
//! Elsewhere both are `None`, and callers go without. And one setting of glibc's allocator that
//! keeps the peak what the estimates say.

/// A `kB` field of a `/proc` status file, in bytes.
fn proc_kb(file: &str, field: &str) -> Option<u64> {
    let text = std::fs::read_to_string(file).ok()?;
    let line = text.lines().find(|l| l.starts_with(field))?;
    let kb: u64 = line[field.len()..]
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kb * 1024)
}

/// Memory the system can still give (`MemAvailable`).
pub fn available_memory() -> Option<u64> {
    proc_kb("/proc/meminfo", "MemAvailable:")
}

/// The memory limit of this process's control group (a container, a farm job), when it has one:
/// cgroup v2 `memory.max`, else v1 `memory.limit_in_bytes` (which reports "no limit" as a huge
/// number, taken as none).
pub fn cgroup_limit() -> Option<u64> {
    let read = |p: &str| std::fs::read_to_string(p).ok();
    let v2 = read("/proc/self/cgroup").and_then(|c| {
        let path = c.lines().find_map(|l| l.strip_prefix("0::"))?.to_string();
        read(&format!(
            "/sys/fs/cgroup{}/memory.max",
            path.trim_end_matches('/')
        ))
        .or_else(|| read("/sys/fs/cgroup/memory.max"))
    });
    let text = v2.or_else(|| read("/sys/fs/cgroup/memory/memory.limit_in_bytes"))?;
    text.trim().parse::<u64>().ok().filter(|&b| b < 1 << 60)
}

/// This process's peak resident memory (`VmHWM`).
pub fn peak_memory() -> Option<u64> {
    proc_kb("/proc/self/status", "VmHWM:")
}

/// Allocations from this size up are mapped on their own and unmapped when freed.
///
/// glibc starts at 128 KiB and raises the threshold to the size of each mapped block freed (up
/// to 32 MiB), so once a bake's lattice frees its per-direction links, the next phase's buffers
/// come from the heap and the freed pages stay resident beside them: measured on a 300³ box of
/// tiles (σt 0.05) the bake peaked at 301 MiB against an estimate of 248 MiB, and at 247 MiB
/// with the threshold fixed at 1 MiB; the torus300 bake 74 → 65 MiB, the half-size cloud's
/// render 223 → 202 MB, times within the machine's noise. Fixed, it no longer moves.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD: i32 = 1 << 20;

/// Fixes glibc's mmap threshold at [`MMAP_THRESHOLD`] (elsewhere: nothing to do).
pub fn return_large_blocks_when_freed() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets an allocator parameter; called before any thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
    }
}
