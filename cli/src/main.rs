//! The `tessera` command: local rendering and benchmarks (farm commands arrive with the farm).

mod bench;
mod client;
mod convergence;
mod farm_cmd;
mod rays;
mod render_cmd;
mod scale;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "tessera", version, about = "Tessera: a distributed path-tracing render farm")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a glTF scene locally to OpenEXR (no server needed).
    Render(render_cmd::RenderArgs),
    /// Measure paths/s and rays/s on a scene (the built-in Cornell box by default); `bench
    /// convergence` measures error against time per technique.
    Bench(bench::BenchArgs),
    /// Run the coordinator: REST API, web page and the workers' gRPC service on one port.
    Coordinator(farm_cmd::CoordinatorArgs),
    /// Run a render worker for a coordinator.
    Worker(farm_cmd::WorkerArgs),
    /// Submit a scene to the farm.
    Submit(client::SubmitArgs),
    /// Show one job (JSON).
    Status(client::StatusArgs),
    /// List jobs.
    List(client::ListArgs),
    /// Cancel a job.
    Cancel(client::JobArgs),
    /// Download a finished job's EXR.
    Download(client::DownloadArgs),
    /// List the workers.
    Workers(client::WorkersArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    // The farm's daemons log what they do (start, jobs, finishes) by default; the commands a user
    // types stay quiet but for warnings. TESSERA_LOG overrides both.
    let default = match cli.command {
        Command::Coordinator(_) | Command::Worker(_) => "info",
        _ => "warn",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_env("TESSERA_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    let builder = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr);
    // TESSERA_LOG_FORMAT=json: one JSON object a line, for log collectors.
    if std::env::var("TESSERA_LOG_FORMAT").is_ok_and(|f| f.eq_ignore_ascii_case("json")) {
        builder.json().init();
    } else {
        // Colours only for a terminal: a log file or a pipe gets plain text.
        builder.with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr())).init();
    }
    let result = match cli.command {
        Command::Render(a) => render_cmd::run(a),
        Command::Bench(a) => bench::run(a),
        Command::Coordinator(a) => farm_cmd::coordinator(a),
        Command::Worker(a) => farm_cmd::worker(a),
        Command::Submit(a) => client::submit(a),
        Command::Status(a) => client::status(a),
        Command::List(a) => client::list(a),
        Command::Cancel(a) => client::cancel(a),
        Command::Download(a) => client::download(a),
        Command::Workers(a) => client::workers(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            match e.downcast_ref::<client::CliError>() {
                Some(c) => std::process::ExitCode::from(c.code),
                None => std::process::ExitCode::FAILURE,
            }
        }
    }
}
