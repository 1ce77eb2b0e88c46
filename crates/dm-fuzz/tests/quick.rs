//! The quick fuzz run of `make test`: every target for a few seconds from
//! the committed corpus (the long run is `make fuzz`). A panic, a hang or
//! an input holding more than `MAX_INPUT_BYTES` of heap fails, printing
//! the input's bytes.

use dm_fuzz::{Budget, Target, default_corpus, run};

#[global_allocator]
static HEAP: dm_fuzz::alloc_meter::MeteredAllocator = dm_fuzz::alloc_meter::MeteredAllocator;

/// Seconds per target: every target gets thousands of inputs.
const QUICK_SECONDS: f64 = 8.0;

fn quick(target: Target) {
    let report = run(
        target,
        &default_corpus(),
        1,
        Budget {
            inputs: u64::MAX,
            seconds: QUICK_SECONDS,
        },
    )
    .unwrap_or_else(|e| panic!("{}: {e}", target.name()));
    assert!(
        report.inputs > 100,
        "{}: only {} inputs",
        target.name(),
        report.inputs
    );
    assert!(
        report.accepted > 0,
        "{}: not even the seeds were accepted",
        target.name()
    );
    // Inputs past `MAX_INPUT_BYTES` are findings; the meter must be on to see them.
    assert!(
        report.largest_input_bytes.is_some_and(|b| b > 0),
        "{}: the heap meter saw nothing",
        target.name()
    );
    if let Some(finding) = report.findings.first() {
        panic!(
            "{}: {} findings; the first, {}, on input {:?}",
            target.name(),
            report.findings.len(),
            finding.what,
            String::from_utf8_lossy(&finding.input)
        );
    }
}

/// The meter sees what a thread holds at its peak, not what it has freed.
#[test]
fn the_heap_meter_sees_a_large_allocation() {
    let start = dm_fuzz::alloc_meter::start();
    let big = std::hint::black_box(vec![0u8; dm_fuzz::MAX_INPUT_BYTES + 1]);
    drop(big);
    let small = std::hint::black_box(vec![0u8; 1024]);
    drop(small);
    assert!(dm_fuzz::alloc_meter::peak_since(start) > dm_fuzz::MAX_INPUT_BYTES);
    let again = dm_fuzz::alloc_meter::start();
    let small = std::hint::black_box(vec![0u8; 1024]);
    drop(small);
    assert!(dm_fuzz::alloc_meter::peak_since(again) < 1 << 20);
}

#[test]
fn pickle() {
    quick(Target::Pickle);
}
#[test]
fn ply() {
    quick(Target::Ply);
}
#[test]
fn obj() {
    quick(Target::Obj);
}
#[test]
fn glb() {
    quick(Target::Glb);
}
#[test]
fn manifest() {
    quick(Target::Manifest);
}
#[test]
fn bundle_json() {
    quick(Target::BundleJson);
}
#[test]
fn bundle_npy() {
    quick(Target::BundleNpy);
}
#[test]
fn model_json() {
    quick(Target::ModelJson);
}
#[test]
fn checkpoint() {
    quick(Target::Checkpoint);
}
#[test]
fn play_command() {
    quick(Target::PlayCommand);
}

/// Every input a fuzz run found (`fuzz/regressions/TARGET/`) is refused
/// with an error, without a panic.
#[test]
fn past_findings_are_refused_without_a_panic_or_a_large_allocation() {
    let root = default_corpus().join("../regressions");
    let mut checked = 0;
    for target in Target::ALL {
        let dir = root.join(target.name());
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for entry in entries {
            let path = entry.expect("entry").path();
            let input = std::fs::read(&path).expect("read");
            let heap = dm_fuzz::alloc_meter::start();
            let accepted = dm_fuzz::feed_once(target, &input)
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            assert!(
                !accepted,
                "{}: a malformed input was accepted",
                path.display()
            );
            let held = dm_fuzz::alloc_meter::peak_since(heap);
            assert!(
                held <= dm_fuzz::MAX_INPUT_BYTES,
                "{}: {} MiB of heap held at once",
                path.display(),
                held >> 20
            );
            checked += 1;
        }
    }
    assert!(checked > 0, "no regression inputs under {}", root.display());
}
