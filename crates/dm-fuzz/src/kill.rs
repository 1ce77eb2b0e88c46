//! Kill and resume: a tool run once to the end, then again and again
//! killed with SIGKILL at seeded random moments and run once more to
//! finish. While each run goes on, and right after each kill, every file at
//! an output path must be whole (written under a temporary name and
//! renamed: an inode never grows once seen, JSON / `.npy` / PLY files
//! parse to their full length); every finished run must hold the
//! uninterrupted run's files, bitwise, but for the wall-clock fields of
//! its JSON reports.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// How often a running tool's output directory is looked at.
const WATCH_INTERVAL: Duration = Duration::from_millis(3);
/// Kill moments are drawn in this part of the uninterrupted run's time.
const KILL_WINDOW: [f64; 2] = [0.02, 0.98];

/// Puts a run's inputs into its output directory before it starts.
pub type Prepare<'a> = &'a dyn Fn(&Path) -> Result<(), String>;

/// A kill-and-resume check of one tool.
pub struct KillCheck<'a> {
    /// The tool writing its outputs under the given directory; `true`
    /// after a kill (the command a user would type to continue). Every
    /// run's directory is named `out`, in a directory of its own, so a
    /// tool that records its command line can be run from the parent
    /// with the same relative path.
    pub command: &'a dyn Fn(&Path, bool) -> Command,
    /// Kill moments.
    pub points: usize,
    pub seed: u64,
    /// Where the runs' output directories go.
    pub scratch: &'a Path,
    /// Puts a run's inputs into its directory before the first start (a
    /// tool that writes beside its input, as dm-appearance into the
    /// model directory).
    pub prepare: Option<Prepare<'a>>,
    /// JSON keys, besides wall-clock ones, that say how the run went rather
    /// than what it computed (e.g. how many results came from a cache).
    pub run_record_keys: &'a [&'a str],
    /// Likewise for text outputs: lines holding one of these are not
    /// compared.
    pub run_record_lines: &'a [&'a str],
}

impl std::fmt::Debug for KillCheck<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("KillCheck")
            .field("points", &self.points)
            .field("seed", &self.seed)
            .field("scratch", &self.scratch)
            .finish_non_exhaustive()
    }
}

/// One kill.
#[derive(Clone, Debug)]
pub struct KillPoint {
    /// Seconds after the start.
    pub after_s: f64,
    /// Files at output paths when it was killed.
    pub files_at_kill: usize,
    /// The run had already finished (the point did not interrupt it).
    pub finished_first: bool,
}

/// What a check saw.
#[derive(Clone, Debug)]
pub struct KillReport {
    /// The uninterrupted run's wall time.
    pub reference_s: f64,
    pub points: Vec<KillPoint>,
    /// Output files looked at while the tools ran or right after a kill.
    pub files_checked: usize,
    /// Temporary files and directories killed runs left beside their
    /// outputs, still there after the rerun.
    pub leftover_temporaries: Vec<PathBuf>,
}

/// Runs the check; the error says which kill point broke what.
pub fn check_kill_and_resume(check: &KillCheck<'_>) -> Result<KillReport, String> {
    let run_dir = |name: &str| -> Result<PathBuf, String> {
        let parent = check.scratch.join(name);
        std::fs::create_dir_all(&parent).map_err(|e| format!("{}: {e}", parent.display()))?;
        Ok(parent.join("out"))
    };
    let reference = run_dir("uninterrupted")?;
    let prepare = |out: &Path| check.prepare.map_or(Ok(()), |p| p(out));
    prepare(&reference)?;
    let mut watch = Watch::default();
    let start = Instant::now();
    let child = spawn(&(check.command)(&reference, false), &reference)?;
    finish(child, &reference, &mut watch, "the uninterrupted run")?;
    let reference_s = start.elapsed().as_secs_f64();
    let expected = output_files(&reference)?;

    let mut rng = ChaCha8Rng::seed_from_u64(check.seed);
    let mut points = Vec::new();
    let mut leftover_temporaries = Vec::new();
    for point in 0..check.points {
        let out = run_dir(&format!("killed{point}"))?;
        let after_s = reference_s * rng.random_range(KILL_WINDOW[0]..KILL_WINDOW[1]);
        let context = format!("kill point {point} ({after_s:.2} s)");
        prepare(&out)?;
        let mut child = spawn(&(check.command)(&out, false), &out)?;
        let started = Instant::now();
        let mut finished_first = false;
        while started.elapsed().as_secs_f64() < after_s {
            watch
                .look(&out)
                .map_err(|e| format!("{context}, running: {e}"))?;
            if child.try_wait().map_err(|e| e.to_string())?.is_some() {
                finished_first = true;
                break;
            }
            std::thread::sleep(WATCH_INTERVAL);
        }
        // SIGKILL: nothing the tool does on exit runs.
        child.kill().ok();
        child.wait().map_err(|e| e.to_string())?;
        let files_at_kill = watch
            .look(&out)
            .map_err(|e| format!("{context}, just killed: {e}"))?;
        points.push(KillPoint {
            after_s,
            files_at_kill,
            finished_first,
        });
        let resumed = spawn(&(check.command)(&out, true), &out)?;
        finish(resumed, &out, &mut watch, &format!("{context}, resumed"))?;
        leftover_temporaries.extend(walk(&out)?.1);
        let got = output_files(&out)?;
        same_outputs(
            &expected,
            &got,
            check.run_record_keys,
            check.run_record_lines,
        )
        .map_err(|e| format!("{context}: {e}"))?;
    }
    Ok(KillReport {
        reference_s,
        points,
        files_checked: watch.files_checked,
        leftover_temporaries,
    })
}

impl KillReport {
    /// Kill points that interrupted the run (the others came after its end).
    pub fn interrupted(&self) -> usize {
        self.points.iter().filter(|p| !p.finished_first).count()
    }

    /// One line for a test's output: what was killed and checked.
    pub fn summary(&self, tool: &str) -> String {
        format!(
            "{tool}: {:.1} s uninterrupted, {} of {} kills interrupted it, {} output files checked whole, {} temporaries left",
            self.reference_s,
            self.interrupted(),
            self.points.len(),
            self.files_checked,
            self.leftover_temporaries.len()
        )
    }
}

/// [`check_kill_and_resume`] for a test: panics with the failure, prints the
/// summary, and requires three in four kill points to have interrupted the
/// run (kill moments are drawn within its uninterrupted length).
pub fn assert_kill_and_resume(tool: &str, check: &KillCheck<'_>) -> KillReport {
    let report = check_kill_and_resume(check).unwrap_or_else(|e| panic!("{tool}: {e}"));
    println!("{}", report.summary(tool));
    assert!(
        report.interrupted() >= check.points * 3 / 4,
        "{tool}: most kills came after the end: {:?}",
        report.points
    );
    report
}

/// Starts `command` with its stderr in a file beside `out` (a pipe nobody
/// reads until the end could fill and stop a talkative tool).
fn spawn(command: &Command, out: &Path) -> Result<Child, String> {
    let mut command = clone_command(command);
    let log = stderr_log(out);
    let stderr = std::fs::File::create(&log).map_err(|e| format!("{}: {e}", log.display()))?;
    command
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(stderr);
    command
        .spawn()
        .map_err(|e| format!("starting {:?}: {e}", command.get_program()))
}

/// Where a run into `out` writes its stderr: beside it, not among its outputs.
fn stderr_log(out: &Path) -> PathBuf {
    out.with_file_name("stderr.txt")
}

/// `Command` is not `Clone`; the check needs a fresh one per run.
fn clone_command(command: &Command) -> Command {
    let mut copy = Command::new(command.get_program());
    copy.args(command.get_args());
    for (key, value) in command.get_envs() {
        match value {
            Some(value) => copy.env(key, value),
            None => copy.env_remove(key),
        };
    }
    if let Some(dir) = command.get_current_dir() {
        copy.current_dir(dir);
    }
    copy
}

/// Watches `out` until `child` ends, which must be a success.
fn finish(mut child: Child, out: &Path, watch: &mut Watch, what: &str) -> Result<(), String> {
    loop {
        watch.look(out).map_err(|e| format!("{what}: {e}"))?;
        if let Some(status) = child.try_wait().map_err(|e| e.to_string())? {
            if !status.success() {
                let stderr = std::fs::read_to_string(stderr_log(out)).unwrap_or_default();
                return Err(format!("{what} failed ({status}): {stderr}"));
            }
            return watch
                .look(out)
                .map(|_| ())
                .map_err(|e| format!("{what}: {e}"));
        }
        std::thread::sleep(WATCH_INTERVAL);
    }
}

/// Whether `name` is a temporary sibling (`NAME.tmp-PID-N` or
/// `NAME.old-PID-N`, as dm-bundle's atomic writers name them, a dm-prep
/// stage's `.STAGE.tmp-PID` directory, or dm-splat's `NAME.tmp`).
fn is_temporary(name: &str) -> bool {
    name.contains(".tmp-") || name.contains(".old-") || name.ends_with(".tmp")
}

/// Files under `dir` at output paths, and the temporary files and
/// directories beside them (not entered).
fn walk(dir: &Path) -> Result<(Vec<PathBuf>, Vec<PathBuf>), String> {
    let (mut files, mut temporaries) = (Vec::new(), Vec::new());
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let entries = match std::fs::read_dir(&d) {
            Ok(entries) => entries,
            // Not made yet, or a temporary directory renamed away meanwhile.
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(format!("{}: {e}", d.display())),
        };
        for entry in entries.flatten() {
            let path = entry.path();
            if is_temporary(&entry.file_name().to_string_lossy()) {
                temporaries.push(path);
                continue;
            }
            match entry.file_type() {
                Ok(t) if t.is_dir() => stack.push(path),
                Ok(t) if t.is_file() => files.push(path),
                _ => {}
            }
        }
    }
    files.sort();
    Ok((files, temporaries))
}

/// A file's identity: device, inode and birth time (a freed inode reused
/// by a later file is born again).
type FileId = (u64, u64, Option<std::time::SystemTime>);

/// Inodes seen at output paths and their sizes: an inode that grows was
/// written in place, where a reader could see it half-written.
#[derive(Default)]
struct Watch {
    sizes: BTreeMap<FileId, (u64, PathBuf)>,
    files_checked: usize,
}

impl Watch {
    /// Checks every file at an output path under `out`; returns how many.
    fn look(&mut self, out: &Path) -> Result<usize, String> {
        let (files, _) = walk(out)?;
        for path in &files {
            let Ok(meta) = std::fs::metadata(path) else {
                continue; // replaced between the listing and now
            };
            let key = (meta.dev(), meta.ino(), meta.created().ok());
            match self.sizes.get(&key) {
                Some((size, seen)) if *size != meta.len() && seen == path => {
                    return Err(format!(
                        "{} changed size in place ({size} → {} bytes): written where a reader sees it",
                        path.display(),
                        meta.len()
                    ));
                }
                Some((size, seen)) if *size == meta.len() && seen == path => continue,
                _ => {}
            }
            self.sizes.insert(key, (meta.len(), path.clone()));
            let Ok(bytes) = std::fs::read(path) else {
                continue;
            };
            // The same inode may have been replaced while being read.
            if std::fs::metadata(path).is_ok_and(|m| m.ino() != meta.ino()) {
                continue;
            }
            whole_file(path, &bytes).map_err(|e| format!("{}: {e}", path.display()))?;
            self.files_checked += 1;
        }
        Ok(files.len())
    }
}

/// Whether `bytes` is a whole file of the type `path` names.
fn whole_file(path: &Path, bytes: &[u8]) -> Result<(), String> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("json") => serde_json::from_slice::<serde_json::Value>(bytes)
            .map(|_| ())
            .map_err(|e| format!("not whole JSON: {e}")),
        Some("npy") => whole_npy(bytes),
        Some("ply") => whole_ply(bytes),
        _ => Ok(()),
    }
}

/// A `.npy` whose data is as long as its header's shape and type say.
fn whole_npy(bytes: &[u8]) -> Result<(), String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not a .npy (no magic)".into());
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        _ if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        _ => return Err("short .npy header".into()),
    };
    let header = bytes
        .get(start..start + header_len)
        .ok_or("short .npy header")?;
    let header = String::from_utf8_lossy(header);
    let item: usize = header
        .split("'descr':")
        .nth(1)
        .and_then(|d| d.split('\'').nth(1))
        .and_then(|d| d.get(2..))
        .and_then(|n| n.parse().ok())
        .ok_or("no item size in the .npy header")?;
    let shape = header
        .split("'shape':")
        .nth(1)
        .and_then(|s| s.split(['(', ')']).nth(1))
        .ok_or("no shape in the .npy header")?;
    let count = shape
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .try_fold(1usize, |n, d| d.parse::<usize>().map(|d| n * d))
        .map_err(|e| format!(".npy shape: {e}"))?;
    let expected = start + header_len + count * item;
    if bytes.len() != expected {
        return Err(format!(
            ".npy holds {} bytes, its header says {expected}",
            bytes.len()
        ));
    }
    Ok(())
}

/// A binary PLY whose vertex data is as long as its header says.
fn whole_ply(bytes: &[u8]) -> Result<(), String> {
    const END: &[u8] = b"end_header\n";
    let end = bytes
        .windows(END.len())
        .position(|w| w == END)
        .ok_or("PLY without end_header")?
        + END.len();
    let header = String::from_utf8_lossy(&bytes[..end]);
    if !header.contains("binary_little_endian") {
        return Ok(()); // ASCII PLY: its length says nothing
    }
    let mut count = 0usize;
    let mut stride = 0usize;
    let mut in_vertex = false;
    for line in header.lines() {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["element", name, n] => {
                in_vertex = *name == "vertex";
                if in_vertex {
                    count = n.parse().map_err(|e| format!("PLY vertex count: {e}"))?;
                }
            }
            ["property", kind, _] if in_vertex => {
                stride += match *kind {
                    "char" | "uchar" | "int8" | "uint8" => 1,
                    "short" | "ushort" | "int16" | "uint16" => 2,
                    "int" | "uint" | "float" | "int32" | "uint32" | "float32" => 4,
                    "double" | "float64" => 8,
                    other => return Err(format!("PLY property type {other}")),
                }
            }
            _ => {}
        }
    }
    if bytes.len() < end + count * stride {
        return Err(format!(
            "PLY holds {} vertex bytes, its header says {}",
            bytes.len() - end,
            count * stride
        ));
    }
    Ok(())
}

/// Relative path → contents of every file at an output path under `dir`.
fn output_files(dir: &Path) -> Result<BTreeMap<PathBuf, Vec<u8>>, String> {
    walk(dir)?
        .0
        .into_iter()
        .map(|path| {
            let bytes = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
            let relative = path.strip_prefix(dir).unwrap_or(&path).to_path_buf();
            Ok((relative, bytes))
        })
        .collect()
}

/// The same files with the same contents; JSON compared without its
/// wall-clock fields (keys naming seconds) and `run_record_keys`, text
/// without the lines holding one of `run_record_lines`.
fn same_outputs(
    expected: &BTreeMap<PathBuf, Vec<u8>>,
    got: &BTreeMap<PathBuf, Vec<u8>>,
    run_record_keys: &[&str],
    run_record_lines: &[&str],
) -> Result<(), String> {
    let names = |m: &BTreeMap<PathBuf, Vec<u8>>| m.keys().cloned().collect::<Vec<_>>();
    if names(expected) != names(got) {
        return Err(format!(
            "other files than the uninterrupted run's: {:?} against {:?}",
            names(got),
            names(expected)
        ));
    }
    for (path, want) in expected {
        let have = &got[path];
        if have == want {
            continue;
        }
        let is_json = path.extension().is_some_and(|e| e == "json");
        let text_without_records = |b: &[u8]| -> Option<Vec<String>> {
            let text = std::str::from_utf8(b).ok()?;
            Some(
                text.lines()
                    .filter(|l| !run_record_lines.iter().any(|r| l.contains(r)))
                    .map(str::to_owned)
                    .collect(),
            )
        };
        if !is_json && !run_record_lines.is_empty() {
            let kept = text_without_records(want);
            if kept.is_some() && kept == text_without_records(have) {
                continue;
            }
        }
        let parsed = |b: &[u8]| {
            serde_json::from_slice::<serde_json::Value>(b).map(|mut v| {
                strip_keys(&mut v, &|key| {
                    key.contains("seconds") || run_record_keys.contains(&key)
                });
                v
            })
        };
        let where_ = match (is_json, parsed(want), parsed(have)) {
            (true, Ok(want), Ok(have)) if want == have => continue,
            (true, Ok(want), Ok(have)) => {
                format!(" at {}", first_difference(&want, &have, String::new()))
            }
            _ => String::new(),
        };
        return Err(format!(
            "{} differs from the uninterrupted run's{where_}",
            path.display()
        ));
    }
    Ok(())
}

/// The JSON path of the first place `a` and `b` differ, with both values.
fn first_difference(a: &serde_json::Value, b: &serde_json::Value, at: String) -> String {
    use serde_json::Value;
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            for (key, value) in x {
                match y.get(key) {
                    Some(other) if other == value => {}
                    Some(other) => return first_difference(value, other, format!("{at}.{key}")),
                    None => return format!("{at}.{key} (missing)"),
                }
            }
            format!("{at} (extra keys)")
        }
        (Value::Array(x), Value::Array(y)) if x.len() == y.len() => x
            .iter()
            .zip(y)
            .position(|(p, q)| p != q)
            .map_or(at.clone(), |i| {
                first_difference(&x[i], &y[i], format!("{at}[{i}]"))
            }),
        _ => format!("{at}: {a} against {b}"),
    }
}

/// Removes the keys `strip` picks from a JSON document, at every depth.
fn strip_keys(value: &mut serde_json::Value, strip: &dyn Fn(&str) -> bool) {
    match value {
        serde_json::Value::Object(map) => {
            map.retain(|key, _| !strip(key));
            map.values_mut().for_each(|v| strip_keys(v, strip));
        }
        serde_json::Value::Array(items) => items.iter_mut().for_each(|v| strip_keys(v, strip)),
        _ => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn truncated_npy_and_ply_files_are_not_whole() {
        let mut npy = b"\x93NUMPY\x01\x00".to_vec();
        let header = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }";
        let mut header = header.to_string();
        while !(10 + header.len() + 1).is_multiple_of(64) {
            header.push(' ');
        }
        header.push('\n');
        npy.extend_from_slice(&(header.len() as u16).to_le_bytes());
        npy.extend_from_slice(header.as_bytes());
        npy.extend_from_slice(&[0u8; 24]);
        assert_eq!(whole_npy(&npy), Ok(()));
        assert!(whole_npy(&npy[..npy.len() - 1]).is_err());

        let mut ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty uchar r\nend_header\n".to_vec();
        ply.extend_from_slice(&[0u8; 10]);
        assert_eq!(whole_ply(&ply), Ok(()));
        assert!(whole_ply(&ply[..ply.len() - 1]).is_err());
    }

    #[test]
    fn reports_compare_without_their_wall_clock() {
        let a = BTreeMap::from([(
            PathBuf::from("r.json"),
            br#"{"loss": 1, "seconds": 2}"#.to_vec(),
        )]);
        let b = BTreeMap::from([(
            PathBuf::from("r.json"),
            br#"{"loss": 1, "seconds": 3}"#.to_vec(),
        )]);
        let c = BTreeMap::from([(
            PathBuf::from("r.json"),
            br#"{"loss": 2, "seconds": 2}"#.to_vec(),
        )]);
        assert_eq!(same_outputs(&a, &b, &[], &[]), Ok(()));
        assert!(same_outputs(&a, &c, &[], &[]).is_err());
        assert_eq!(same_outputs(&a, &c, &["loss"], &[]), Ok(()));
        let d = BTreeMap::from([(PathBuf::from("t.md"), b"a\n2 runs (0 cached)\nb\n".to_vec())]);
        let e = BTreeMap::from([(PathBuf::from("t.md"), b"a\n2 runs (1 cached)\nb\n".to_vec())]);
        let f = BTreeMap::from([(PathBuf::from("t.md"), b"a\n2 runs (1 cached)\nc\n".to_vec())]);
        assert!(same_outputs(&d, &e, &[], &[]).is_err());
        assert_eq!(same_outputs(&d, &e, &[], &["cached)"]), Ok(()));
        assert!(same_outputs(&d, &f, &[], &["cached)"]).is_err());
    }

    /// A writer that writes its output in place is caught while it runs.
    #[test]
    fn a_file_written_in_place_is_caught() {
        let dir = tempfile::tempdir().expect("temp dir");
        let script =
            "for i in $(seq 1 400); do printf 0123456789 >> \"$1/out.txt\"; sleep 0.002; done";
        let command = |out: &Path, _resume: bool| {
            let mut c = Command::new("sh");
            c.arg("-c")
                .arg(format!("mkdir -p \"$1\" && {script}"))
                .arg("sh")
                .arg(out);
            c
        };
        let check = KillCheck {
            command: &command,
            points: 1,
            seed: 1,
            scratch: dir.path(),
            prepare: None,
            run_record_keys: &[],
            run_record_lines: &[],
        };
        let error = check_kill_and_resume(&check).expect_err("in-place writes are found");
        assert!(error.contains("changed size in place"), "{error}");
    }
}
