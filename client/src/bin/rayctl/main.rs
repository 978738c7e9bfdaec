//! `rayctl`: the command-line client of rayd. Parsing lives in [`args`], the work in `rayd-client`, the printing
//! in [`show`]. Errors print `error: <gRPC code>: <message>` and exit with 1; usage errors exit with 2 (clap). A
//! reader of the output that has gone (`rayctl … | head`, the report's or the data's: `--out /dev/stdout`) ends
//! rayctl quietly, with 0.

mod args;
mod bounced;
mod commands;
mod parts;
mod show;

use std::io::{self, Write};
use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    let cli = args::Cli::parse();
    let runtime = match tokio::runtime::Runtime::new() {
        Ok(runtime) => runtime,
        Err(e) => return failure(&format!("Internal: cannot start tokio's runtime: {e}")),
    };
    let code = runtime.block_on(async {
        match commands::run(&cli).await {
            Ok(output) => report(&if cli.json { output.json.to_string() } else { output.text }),
            // Data for a reader that has gone (`rayctl trace --out /dev/stdout … | head`).
            Err(rayd_client::Error::Io { source, .. }) if source.kind() == io::ErrorKind::BrokenPipe => {
                ExitCode::SUCCESS
            }
            Err(error) => failure(&format!("{:?}: {error}", error.code())),
        }
    });
    // Without waiting for reads on blocking threads: one given up at Ctrl-C may wait on a pipe that stays open.
    runtime.shutdown_background();
    code
}

/// How long a command's clean-up (temporary buffers, a failed scene's accels) may take: a server that does not
/// answer (often why the command failed) does not hold rayctl.
const CLEAN_UP_TIME: std::time::Duration = std::time::Duration::from_secs(10);

/// Prints `warning: <message>` on standard error: what a command left undone beside its outcome.
fn warn(message: &str) {
    // Nothing is left to do if standard error has gone.
    let _ = writeln!(io::stderr(), "warning: {message}");
}

/// Prints `error: <message>` on standard error; failure.
fn failure(message: &str) -> ExitCode {
    // Nothing is left to do if standard error has gone too.
    let _ = writeln!(io::stderr(), "error: {message}");
    ExitCode::FAILURE
}

/// Prints the report `text` and a newline on standard output, or on standard error where data went to standard
/// output (`--out /dev/stdout`): success, also when the reader has gone (a closed pipe), as other command-line tools
/// end; any other failure to write is an error.
fn report(text: &str) -> ExitCode {
    let written = if parts::standard_output_taken() {
        writeln!(io::stderr(), "{text}")
    } else {
        let mut stdout = io::stdout().lock();
        writeln!(stdout, "{text}").and_then(|()| stdout.flush())
    };
    match written {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if e.kind() == io::ErrorKind::BrokenPipe => ExitCode::SUCCESS,
        Err(e) => failure(&format!("standard output: {e}")),
    }
}
