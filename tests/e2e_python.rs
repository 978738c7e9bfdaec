//! The contract works outside Rust: a Python `grpcio` client generated from `proto/` by grpcio-tools builds and
//! traces against the real `rayd` (`tests/python/contract_test.py`).
//!
//! Python comes from a virtual environment at `target/python-venv`, made once with the pinned packages of
//! `tests/python/requirements.txt` and made again when they change. Without PyPI this test fails, with pip's
//! message: it never skips.

mod daemon;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use daemon::Daemon;

/// The packages the venv was made with; a venv made with others is made again.
const REQUIREMENTS: &str = include_str!("python/requirements.txt");

/// Runs `command`, panicking with its output unless it succeeds.
fn run(command: &mut Command, what: &str) -> Output {
    let output = command.output().unwrap_or_else(|e| panic!("{what}: {e}"));
    assert!(
        output.status.success(),
        "{what}: {}\n--- stdout\n{}--- stderr\n{}",
        output.status,
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

/// The venv's interpreter, after making the venv if it does not hold exactly [`REQUIREMENTS`].
fn python() -> PathBuf {
    let venv = daemon::target_dir().join("python-venv");
    let python = venv.join("bin").join("python");
    let installed = venv.join("rayd-requirements.txt");
    if std::fs::read_to_string(&installed).is_ok_and(|text| text == REQUIREMENTS) {
        return python;
    }
    run(Command::new("python3").args(["-m", "venv", "--clear"]).arg(&venv), "python3 -m venv");
    let requirements = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/requirements.txt");
    let mut pip = Command::new(&python);
    pip.args(["-m", "pip", "install", "--disable-pip-version-check", "--requirement"]).arg(requirements);
    run(&mut pip, "pip install --requirement tests/python/requirements.txt (it needs PyPI)");
    std::fs::write(&installed, REQUIREMENTS).expect("the venv's stamp can be written");
    python
}

/// Generates the Python messages and stubs of every `.proto` file of `proto/` into `target/tmp/python-stubs`, made anew.
fn generate_stubs(python: &Path) -> PathBuf {
    let out = Path::new(env!("CARGO_TARGET_TMPDIR")).join("python-stubs");
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir_all(&out).expect("the stub directory can be created");
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    // Relative to `root`, so that protoc sees them under --proto_path.
    let mut protos: Vec<PathBuf> = std::fs::read_dir(root.join("proto/rayd/v1"))
        .expect("proto/rayd/v1 is readable")
        .map(|entry| Path::new("proto/rayd/v1").join(entry.expect("a directory entry").file_name()))
        .filter(|path| path.extension().is_some_and(|e| e == "proto"))
        .collect();
    protos.sort();
    let mut protoc = Command::new(python);
    protoc.current_dir(root).args(["-m", "grpc_tools.protoc", "--proto_path=proto"]);
    protoc.arg(format!("--python_out={}", out.display())).arg(format!("--grpc_python_out={}", out.display()));
    run(protoc.args(&protos), "grpc_tools.protoc");
    out
}

#[test]
fn a_python_client_generated_from_the_proto_files_builds_and_traces() {
    let python = python();
    let stubs = generate_stubs(&python);
    let daemon = Daemon::start(&[]);
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/contract_test.py");
    let mut contract = Command::new(&python);
    contract.arg(script).arg("--address").arg(daemon.grpc_addr().to_string()).arg("--stubs").arg(&stubs);
    let output = run(&mut contract, "tests/python/contract_test.py");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(stdout.contains("contract ok: 6 rays, 3 hits, prim_ids [10, 11, -1, -1, 10, -1]"), "{stdout}");
}
