//! The CUDA driver emulated on the CPU, for tests without a GPU:
//! `emulator/driver.cc` implements the driver calls the backend makes and
//! runs the kernels, compiled as C++ from the same sources, one block at a
//! time (docs/gpu.md, "Checks"). [`build`] compiles it into a `libcuda.so`
//! that a process loads with `LD_PRELOAD` in place of the driver.

use crate::Precision;
use crate::kernels::{ENTRY_POINTS, RESIDUAL_ENTRY_POINTS, source};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The kernels of both precisions as one C++ unit, each in a namespace of
/// its own, registered with the emulator by name.
fn emulated_unit() -> String {
    let mut unit = String::from("#include \"kernel_shim.h\"\n");
    let precisions = [(Precision::F32, "float"), (Precision::F64, "double")];
    for (precision, name) in precisions {
        // C linkage would give both precisions' kernels one symbol.
        let kernels = source(precision).replace("extern \"C\" __global__", "__global__");
        unit.push_str(&format!(
            "#undef REAL\nnamespace dm_{name} {{\nDM_EMU_BUILTINS\n{kernels}\n}}\n"
        ));
    }
    unit.push_str("namespace {\nstruct Registration {\n    Registration() {\n");
    for (_, name) in precisions {
        for entry in ENTRY_POINTS.iter().chain(&RESIDUAL_ENTRY_POINTS) {
            unit.push_str(&format!(
                "        using T_{name}_{entry} = dm_emu::Thunk<&dm_{name}::{entry}>;\n        dm_emu_register(\"{name}\", \"{entry}\", &T_{name}_{entry}::run, T_{name}_{entry}::param_count, T_{name}_{entry}::param_sizes);\n"
            ));
        }
    }
    unit.push_str("    }\n} registration;\n}\n");
    unit
}

/// Builds the emulator into `dir` (created) with `$CXX`, else the first of
/// `c++` and `clang++` found, and returns the library's path.
pub fn build(dir: &Path) -> Result<PathBuf, String> {
    let sources = Path::new(env!("CARGO_MANIFEST_DIR")).join("emulator");
    std::fs::create_dir_all(dir).map_err(|e| format!("creating {}: {e}", dir.display()))?;
    let unit = dir.join("kernels.cc");
    std::fs::write(&unit, emulated_unit())
        .map_err(|e| format!("writing {}: {e}", unit.display()))?;
    let library = dir.join("libcuda.so");
    let include = sources.to_string_lossy().into_owned();
    let driver = sources.join("driver.cc").to_string_lossy().into_owned();
    compile(
        "the CUDA emulator",
        &[
            "-std=c++17",
            "-O1",
            "-fPIC",
            "-shared",
            "-Wl,-soname,libcuda.so",
            "-I",
            &include,
            &driver,
            &unit.to_string_lossy(),
            "-o",
            &library.to_string_lossy(),
        ],
    )?;
    Ok(library)
}

/// Builds `emulator/checks/NAME.cc`, a program that calls the emulated
/// driver directly, linked against `library` (from [`build`]), into the
/// library's folder; returns the program's path. Run it with the library's
/// folder on `LD_LIBRARY_PATH`.
pub fn build_check(name: &str, library: &Path) -> Result<PathBuf, String> {
    let source = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("emulator/checks")
        .join(format!("{name}.cc"));
    let dir = library.parent().unwrap_or(Path::new("."));
    let program = dir.join(name);
    compile(
        name,
        &[
            "-std=c++17",
            "-O1",
            &source.to_string_lossy(),
            &library.to_string_lossy(),
            "-o",
            &program.to_string_lossy(),
        ],
    )?;
    Ok(program)
}

/// Runs a tool's `command` with `--device DEVICE` appended, under the
/// emulator `library` (from [`build`]) in place of the driver when DEVICE
/// is `cuda`; a failed run's error names the device and carries the
/// tool's standard error.
pub fn run_on_device(
    command: &mut Command,
    device: &str,
    library: &Path,
) -> Result<std::process::Output, String> {
    command.args(["--device", device]);
    if device == "cuda" {
        command.env("LD_PRELOAD", library);
    }
    let output = command
        .output()
        .map_err(|e| format!("{device}: {:?} did not start: {e}", command.get_program()))?;
    if !output.status.success() {
        return Err(format!(
            "{device}: {:?} failed ({}):\n{}",
            command.get_program(),
            output.status,
            String::from_utf8_lossy(&output.stderr)
        ));
    }
    Ok(output)
}

/// Runs `$CXX`, else the first of `c++` and `clang++` found, on `args`.
fn compile(what: &str, args: &[&str]) -> Result<(), String> {
    let compilers = std::env::var("CXX")
        .map(|c| vec![c])
        .unwrap_or_else(|_| vec!["c++".into(), "clang++".into()]);
    for compiler in &compilers {
        let Ok(output) = Command::new(compiler).args(args).output() else {
            continue;
        };
        if !output.status.success() {
            return Err(format!(
                "{compiler} could not build {what}:\n{}",
                String::from_utf8_lossy(&output.stderr)
            ));
        }
        return Ok(());
    }
    Err(format!(
        "no C++ compiler found (tried {compilers:?}); set CXX"
    ))
}
