//! `rayctl`: the command-line client of rayd. Parsing lives in [`args`], the work in `rayd-client`, the printing
//! in [`show`]. Errors print `error: <gRPC code>: <message>` and exit with 1; usage errors exit with 2 (clap).

mod args;
mod commands;
mod show;

use std::process::ExitCode;

use clap::Parser;

#[tokio::main]
async fn main() -> ExitCode {
    let cli = args::Cli::parse();
    match commands::run(&cli).await {
        Ok(output) => {
            if cli.json {
                println!("{}", output.json);
            } else {
                println!("{}", output.text);
            }
            ExitCode::SUCCESS
        }
        Err(error) => {
            eprintln!("error: {:?}: {error}", error.code());
            ExitCode::FAILURE
        }
    }
}
