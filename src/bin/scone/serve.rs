//! `scone serve`: the gRPC + HTTP service.

use std::path::PathBuf;

use clap::Args;

/// Run the gRPC + HTTP service (settings: defaults, then --config / SCONE_CONFIG, then SCONE_<SECTION>__<KEY>
/// environment variables, then these flags).
#[derive(Args)]
pub struct ServeArgs {
    /// TOML settings file.
    #[arg(long, env = "SCONE_CONFIG")]
    pub config: Option<PathBuf>,
    /// gRPC listen address.
    #[arg(long)]
    pub grpc_addr: Option<std::net::SocketAddr>,
    /// HTTP listen address.
    #[arg(long)]
    pub http_addr: Option<std::net::SocketAddr>,
    /// Directory of the maps.
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    /// SConE ONNX model.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Print the effective settings (without keys) as JSON and exit.
    #[arg(long)]
    pub print_settings: bool,
}

pub fn run(args: ServeArgs) -> anyhow::Result<()> {
    let ServeArgs { config, grpc_addr, http_addr, data_dir, model, print_settings } = args;
    let overrides = scone::settings::Overrides { grpc_addr, http_addr, data_dir, model };
    let settings = scone::settings::Settings::load(config.as_deref(), &overrides)?;
    if print_settings {
        println!("{}", serde_json::to_string_pretty(&settings.redacted())?);
        return Ok(());
    }
    let runtime =
        tokio::runtime::Builder::new_multi_thread().worker_threads(2).thread_name("scone-io").enable_all().build()?;
    runtime.block_on(scone::server::run(settings))?;
    Ok(())
}
