//! The `scone` command: the service (`serve`) and the offline tools, one file per command group.

use clap::{Parser, Subcommand};

mod args;
mod eval;
mod features;
mod map;
mod serve;

#[derive(Parser)]
#[command(name = "scone", version, about = "SConE image matching and relocalisation")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the gRPC + HTTP service (settings: defaults, then --config / SCONE_CONFIG, then SCONE_<SECTION>__<KEY>
    /// environment variables, then these flags).
    Serve(serve::ServeArgs),
    /// Extract FAST + FREAK features and constellations from one image and print a summary as JSON.
    Extract(features::ExtractArgs),
    /// Evaluate on a real scene (the paper's protocol).
    #[command(subcommand)]
    Eval(Box<eval::EvalCommand>),
    /// Maps on disk, through the same store the service uses.
    #[command(subcommand)]
    Map(map::MapCommand),
    /// Export a scene's features and constellations to an .npz file for training.
    Features(features::FeaturesArgs),
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    match Cli::parse().command {
        Command::Serve(args) => serve::run(args),
        Command::Extract(args) => features::extract(args),
        Command::Eval(cmd) => eval::run(*cmd),
        Command::Map(cmd) => map::run(cmd),
        Command::Features(args) => features::export(args),
    }
}
