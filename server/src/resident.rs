//! Gives the binary's start-up code back to the kernel once the broker
//! serves (Linux only; docs/performance.md, "Idle memory").
//!
//! Starting runs code an idle or busy broker never runs again: the command
//! line and config parsers, the store's recovery, the password hash of the
//! default user, the routers built once. The kernel keeps every page of
//! the binary a process touched resident, so that code stayed in the idle
//! broker's resident memory (1.5 MB of its 3.2 MB of code and data at
//! d00f8a3). Once the start is over ([`START_SETTLES`] after the
//! listeners open), [`release_start_up_code`] asks the kernel to reclaim the binary's pages that are still the file's own
//! (`MADV_PAGEOUT` on its read-only mappings that hold no private copy):
//! nothing changes for the program, a page it runs again is mapped back
//! from the page cache (or the disk, if the kernel dropped it there too)
//! at its next use. `server/link/hot-text.ld` keeps the code the broker
//! runs packed together, so what comes back is a few dense windows.
//!
//! Uses the standard library, rustix and tokio; the broker's crates know
//! nothing of it (an embedder's program is its own to manage).

/// The binary's read-only mappings that hold nothing but the file's own
/// pages, as `(start, length)`, from `smaps` (the text of
/// `/proc/self/smaps`) for the executable at `exe`: a mapping the program
/// or the loader wrote to (relocated read-only data) holds private copies
/// (`Anonymous:` above 0 kB), which reclaiming would swap out, so it is
/// left alone.
fn unwritten_mappings_of(smaps: &str, exe: &str) -> Vec<(usize, usize)> {
    let mut found = Vec::new();
    let mut current: Option<(usize, usize)> = None;
    for line in smaps.lines() {
        let mut fields = line.split_whitespace();
        let first = fields.next().unwrap_or_default();
        if let Some((start, end)) = first.split_once('-') {
            let perms = fields.next().unwrap_or_default();
            let path = fields.nth(3);
            let range =
                (usize::from_str_radix(start, 16).ok()).zip(usize::from_str_radix(end, 16).ok());
            current = match (range, path) {
                (Some((start, end)), Some(path))
                    if path == exe && perms.starts_with('r') && !perms.contains('w') =>
                {
                    Some((start, end - start))
                }
                _ => None,
            };
        } else if first == "Anonymous:" {
            if let Some(mapping) = current.take() {
                if fields.next() == Some("0") {
                    found.push(mapping);
                }
            }
        }
    }
    found
}

/// How long after the listeners open the start is taken to be over: the
/// operators' listeners finish starting on their own thread, and the
/// sweepers, the store's flusher and the status page's sampler run their
/// first rounds. Given back earlier, their start-up code came back: the
/// binary's part settled at 2.4-2.7 MB instead of 1.7-1.9 (four runs with
/// `--log debug`, the advice given again from outside 15 s after start).
const START_SETTLES: std::time::Duration = std::time::Duration::from_secs(5);

/// Waits [`START_SETTLES`], then asks the kernel to reclaim the binary's
/// start-up code (module docs), in a blocking thread of the runtime: the
/// advice walks the mappings' pages (under a millisecond here, but not
/// the broker's thread to spend). An error (an older kernel without
/// `MADV_PAGEOUT`, before Linux 5.4) leaves the pages as they are.
pub async fn release_start_up_code() {
    tokio::time::sleep(START_SETTLES).await;
    let given_back = tokio::task::spawn_blocking(give_back_start_up_code).await;
    match given_back
        .map_err(std::io::Error::other)
        .and_then(|given| given)
    {
        Ok(bytes) => tracing::debug!(bytes, "start-up code given back to the kernel"),
        Err(e) => tracing::debug!(error = %e, "start-up code kept resident"),
    }
}

/// [`release_start_up_code`]'s work: how many bytes of mappings were
/// advised.
#[cfg(target_os = "linux")]
fn give_back_start_up_code() -> std::io::Result<usize> {
    let exe = std::fs::read_link("/proc/self/exe")?;
    let smaps = std::fs::read_to_string("/proc/self/smaps")?;
    let mut advised = 0;
    for (start, length) in unwritten_mappings_of(&smaps, &exe.to_string_lossy()) {
        // SAFETY: advice on a read-only, file-backed mapping of this
        // executable that holds no private page: reclaiming changes no
        // byte the program reads (a page comes back from the file), and
        // the range is exactly one mapping the kernel listed.
        #[allow(unsafe_code)]
        unsafe {
            rustix::mm::madvise(
                start as *mut std::ffi::c_void,
                length,
                rustix::mm::Advice::LinuxPageOut,
            )?;
        }
        advised += length;
    }
    Ok(advised)
}

/// Elsewhere the pages stay as they are.
#[cfg(not(target_os = "linux"))]
fn give_back_start_up_code() -> std::io::Result<usize> {
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    const SMAPS: &str = "\
55d0a0000000-55d0a0200000 r--p 00000000 fd:01 42 /usr/bin/leveret
Size:               2048 kB
Rss:                 700 kB
Anonymous:             0 kB
55d0a0200000-55d0a0c00000 r-xp 00200000 fd:01 42 /usr/bin/leveret
Size:              10240 kB
Anonymous:             0 kB
55d0a0c00000-55d0a0c50000 r--p 00c00000 fd:01 42 /usr/bin/leveret
Size:                320 kB
Anonymous:           320 kB
55d0a0c50000-55d0a0c54000 rw-p 00c50000 fd:01 42 /usr/bin/leveret
Anonymous:             8 kB
7f0000000000-7f0000100000 r-xp 00000000 fd:01 7 /usr/lib/x86_64-linux-gnu/libc.so.6
Anonymous:             0 kB
7f0000200000-7f0000300000 rw-p 00000000 00:00 0
Anonymous:           512 kB
7ffd00000000-7ffd00021000 rw-p 00000000 00:00 0 [stack]
Anonymous:            84 kB
";

    #[test]
    fn only_the_binarys_unwritten_read_only_mappings_are_advised() {
        assert_eq!(
            unwritten_mappings_of(SMAPS, "/usr/bin/leveret"),
            [(0x55d0a0000000, 0x200000), (0x55d0a0200000, 0xa00000)],
            "the relocated read-only data, the writable data, the libraries \
             and anonymous memory are left alone"
        );
    }

    #[test]
    fn another_binarys_mappings_are_not_advised() {
        assert!(unwritten_mappings_of(SMAPS, "/usr/bin/other").is_empty());
        assert!(unwritten_mappings_of("", "/usr/bin/leveret").is_empty());
    }

    /// Resident kB of the executable's own mappings.
    #[cfg(target_os = "linux")]
    fn binary_resident_kb() -> u64 {
        let exe = std::fs::read_link("/proc/self/exe").unwrap();
        let exe = exe.to_string_lossy();
        let smaps = std::fs::read_to_string("/proc/self/smaps").unwrap();
        let (mut ours, mut kb) = (false, 0);
        for line in smaps.lines() {
            let mut fields = line.split_whitespace();
            match fields.next() {
                Some(range) if range.contains('-') => ours = fields.nth(4) == Some(&*exe),
                Some("Rss:") if ours => kb += fields.next().unwrap().parse::<u64>().unwrap(),
                _ => {}
            }
        }
        kb
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn the_binarys_pages_are_reclaimed_and_its_code_and_data_still_serve() {
        let before = binary_resident_kb();
        let advised = give_back_start_up_code().expect("MADV_PAGEOUT (Linux 5.4+)");
        let after = binary_resident_kb();
        assert!(advised > 0, "the test binary's code was advised");
        assert!(
            after < before,
            "resident {before} kB before, {after} kB after"
        );
        // The code and the read-only data paged out come back from the file.
        assert_eq!(unwritten_mappings_of(SMAPS, "/usr/bin/leveret").len(), 2);
    }
}
