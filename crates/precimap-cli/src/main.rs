//! `precimap`: simulate campaigns, adjust them, evaluate against truth, benchmark.

/// `println!` that ends the process quietly when stdout is a closed pipe (`precimap evaluate |
/// head`): Rust ignores SIGPIPE, so `println!` would panic there.
macro_rules! outln {
    ($($arg:tt)*) => {
        $crate::write_stdout_line(format_args!($($arg)*))
    };
}

mod accuracy;
mod bench;
mod progress;
mod segments;
mod service;
mod storage_args;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(name = "precimap", version, about = "Strip adjustment of mobile-mapping LiDAR to millimetre-consistent maps")]
struct Cli {
    /// Worker threads (default: all cores).
    #[arg(long, global = true, env = "PRECIMAP_THREADS")]
    threads: Option<usize>,
    /// Log lines as text, or as JSON objects (one a line, with a task's campaign, task id, kind,
    /// key and attempt as fields) for a log collector. The filter is PRECIMAP_LOG (default warn).
    #[arg(long, global = true, env = "PRECIMAP_LOG_FORMAT", default_value = "text")]
    log_format: LogFormat,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Write a simulated campaign (manifest, LAS strips, trajectories) and its truth.
    Simulate {
        #[arg(long, default_value = "small")]
        scale: precimap_sim::Scale,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        #[arg(long)]
        out: PathBuf,
        /// Write LAZ instead of LAS.
        #[arg(long)]
        laz: bool,
        /// Also write the campaign as it comes from the field into OUT/field: SBET trajectories in
        /// geographic coordinates and strips in WGS 84 / UTM zone 32N with adjusted standard GPS
        /// time, with a manifest whose processing frame is the simulation's local frame.
        #[arg(long)]
        field: bool,
        /// Measurements per scanner revolution instead of the scale's (small 240, i.e. 1.5°;
        /// real mobile-mapping heads take ~3000); must divide 60000.
        #[arg(long)]
        points_per_revolution: Option<u32>,
        /// Scanner revolutions per second instead of the scale's (small 40, medium 100).
        #[arg(long)]
        revolutions_per_s: Option<f64>,
        /// Start from this simulation config (JSON, as `truth/truth.json`'s `config`) instead of
        /// the scale's preset; the other options change it.
        #[arg(long, value_name = "JSON_FILE")]
        config: Option<PathBuf>,
        /// The town: grid, oblique (streets at 65°/115°), open_road or downtown.
        #[arg(long)]
        scene: Option<precimap_sim::Scene>,
        /// The pose and calibration errors: sinusoids, gauss_markov, gauss_markov_slow,
        /// random_walk, white_noise, outage or calibration.
        #[arg(long)]
        errors: Option<precimap_sim::ErrorModel>,
        /// Passes (each drives the figure 8 once).
        #[arg(long)]
        passes: Option<u32>,
        /// Scan heads per vehicle (1 or 2).
        #[arg(long)]
        heads: Option<u32>,
        /// One multi-beam spinning head on the roof (32 rings over −25°…+15°, 10 Hz, 1000 firings
        /// per revolution) instead of the profile heads; its strips carry the ring in the LAS
        /// user-data byte. `--revolutions-per-s` then sets its spin rate.
        #[arg(long)]
        multibeam: bool,
        /// Rings of the multi-beam head (2–255).
        #[arg(long, requires = "multibeam")]
        rings: Option<u32>,
        /// Firings per revolution of the multi-beam head; must divide 60000.
        #[arg(long, requires = "multibeam")]
        firings_per_revolution: Option<u32>,
        #[command(flatten)]
        control: ControlArgs,
    },
    /// Adjust a campaign: corrected strips, trajectories and report.json in OUT. Runs through the
    /// job framework on the embedded default (SQLite + local store + in-process executors).
    Run {
        manifest: PathBuf,
        #[arg(long)]
        out: PathBuf,
        /// Keep the job database and object store (OUT/.precimap), or with --in-process the tile
        /// chunks (OUT/work).
        #[arg(long)]
        keep_work: bool,
        /// Bypass the job framework: the in-process driver (rayon over tiles and trajectories).
        #[arg(long)]
        in_process: bool,
        /// With --in-process: also write the surface model every point was compared with after
        /// the last iteration (OUT/assignments; `evaluate` reports the wrong-assignment share).
        #[arg(long, requires = "in_process")]
        assignments: bool,
    },
    /// Serve the REST API (and optionally in-process executors).
    Serve(service::ServeArgs),
    /// Run executors: claim tasks from the job store, run them, commit their outputs.
    Work(service::WorkArgs),
    /// Upload the files a local manifest names to a server and submit the campaign; prints its id.
    Submit {
        manifest: PathBuf,
        #[command(flatten)]
        client: service::ClientArgs,
    },
    /// Show a campaign's state, stage, iteration and task counts.
    Status {
        id: uuid::Uuid,
        /// Keep showing until the campaign has finished.
        #[arg(long)]
        watch: bool,
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        client: service::ClientArgs,
    },
    /// Download a finished campaign's corrected strips, trajectories and report.
    Results {
        id: uuid::Uuid,
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        client: service::ClientArgs,
    },
    /// Stop a running campaign.
    Cancel {
        id: uuid::Uuid,
        #[command(flatten)]
        client: service::ClientArgs,
    },
    /// Remove a finished campaign and its objects.
    Delete {
        id: uuid::Uuid,
        #[command(flatten)]
        client: service::ClientArgs,
    },
    /// Compare a result with the simulator's truth, before and after.
    Evaluate {
        /// The campaign's truth folder (CAMPAIGN/truth), or the campaign folder itself.
        #[arg(long)]
        truth: PathBuf,
        /// The folder `precimap run` wrote.
        #[arg(long)]
        result: PathBuf,
        /// Print one JSON object.
        #[arg(long)]
        json: bool,
    },
    /// Print the estimation parameters a run would use, as the JSON a manifest's `parameters`
    /// takes: the defaults, or those of MANIFEST (its overrides on the defaults). Copy, edit and
    /// paste back, e.g. to repeat the schedule's last step so that a campaign runs on.
    Parameters { manifest: Option<PathBuf> },
    /// Simulate, run and evaluate in one go (the README's first command).
    Demo {
        #[arg(long, default_value = "small")]
        scale: precimap_sim::Scale,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        #[arg(long, default_value = "demo")]
        out: PathBuf,
    },
    /// Segment one strip in its scan image; draw the segments (--png).
    Segments(segments::SegmentsArgs),
    /// Benchmarks printing per-core throughput.
    Bench {
        #[command(subcommand)]
        what: bench::BenchCommand,
    },
}

pub(crate) fn write_stdout_line(args: std::fmt::Arguments<'_>) {
    use std::io::Write as _;
    let mut out = std::io::stdout().lock();
    if let Err(e) = out.write_fmt(args).and_then(|()| out.write_all(b"\n")) {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            std::process::exit(0);
        }
        eprintln!("error: writing to stdout: {e}");
        std::process::exit(1);
    }
}

fn main() {
    // Parsed before the process executes itself again (`tune_glibc_malloc`), which needs the
    // subcommand; the new image parses the same arguments again.
    let cli = Cli::parse();
    tune_glibc_malloc(MallocTuning::of(&cli));
    if let Err(e) = real_main(cli) {
        eprintln!("error: {}", error_chain(&e));
        std::process::exit(1);
    }
}

/// glibc gives a thread that meets contention an arena of its own, up to eight per core, and keeps
/// what is freed in each: without a limit ~40 % of `bench estimate`'s peak RSS on medium was such
/// kept memory, and one arena per core cost no speed (docs/design/estimation.md, "Throughput"). glibc reads
/// its settings once, at its first allocation, so the process executes itself again (same pid,
/// arguments and streams) with that limit and the command's [`MallocTuning`] in its environment,
/// keeping any of the tuning's variables the user set. A limit already set (by the user, who then
/// chooses every setting, or by this restart), or a failed exec, leaves the process as it is.
#[cfg_attr(not(all(target_os = "linux", target_env = "gnu")), allow(unused_variables))]
fn tune_glibc_malloc(tuning: MallocTuning) {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use std::os::unix::process::CommandExt as _;
        const MALLOC_ARENA_MAX: &str = "MALLOC_ARENA_MAX";
        if std::env::var_os(MALLOC_ARENA_MAX).is_some() {
            return;
        }
        let Ok(exe) = std::env::current_exe() else { return };
        let mut args = std::env::args_os();
        let mut command = std::process::Command::new(exe);
        if let Some(name) = args.next() {
            command.arg0(name);
        }
        for &(variable, value) in tuning.environment() {
            if std::env::var_os(variable).is_none() {
                command.env(variable, value.to_string());
            }
        }
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        // `exec` returns only when it failed; then carry on as we are.
        let error = command.args(args).env(MALLOC_ARENA_MAX, cores.to_string()).exec();
        eprintln!(
            "warning: could not restart with {MALLOC_ARENA_MAX}={cores} ({error}); continuing with glibc's defaults"
        );
    }
}

/// How glibc's allocator treats large blocks, per command.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum MallocTuning {
    /// `evaluate`: blocks from [`EVALUATE_MMAP_THRESHOLD`] up are mapped on their own and returned
    /// when freed. glibc's own threshold rises to the size of the largest block freed (up to
    /// 32 MiB), so a strip's arrays (tens of MB) would come from the heap after the first strip,
    /// and the heap would keep them; the latent map is then read on top of every strip's arrays.
    /// On large s1: peak 2.52 → 1.64 GB, time unchanged.
    ReturnLargeBlocks,
    /// Everything else (the tasks): freed memory stays in the heap for the next task. With
    /// glibc's defaults the heap is trimmed whenever 128 KiB–64 MiB lie free at its top, and the
    /// next tile faults every page of it in again, zeroed by the kernel: on large s1 27 % of a
    /// 2 cm pass's CPU was the kernel's, 6 % with this tuning, and the pass ran 1.36× the points
    /// per CPU-second at a 3 % higher peak (docs/design/estimation.md, "Throughput").
    KeepFreedMemory,
}

/// Blocks from this size up are mapped on their own and returned when freed, in `evaluate`.
#[cfg_attr(not(all(target_os = "linux", target_env = "gnu")), allow(dead_code))]
const EVALUATE_MMAP_THRESHOLD: usize = 1 << 20;

/// glibc's largest mmap threshold on 64-bit (half its 64 MiB arena heap; a larger value is
/// ignored): blocks above it are always mapped on their own.
#[cfg_attr(not(all(target_os = "linux", target_env = "gnu")), allow(dead_code))]
const TASK_MMAP_THRESHOLD: usize = 32 << 20;

/// Free memory at the heap's top up to this size stays mapped: in effect, never trim.
#[cfg_attr(not(all(target_os = "linux", target_env = "gnu")), allow(dead_code))]
const TASK_TRIM_THRESHOLD: usize = usize::MAX / 2;

impl MallocTuning {
    fn of(cli: &Cli) -> Self {
        match cli.command {
            Command::Evaluate { .. } => Self::ReturnLargeBlocks,
            _ => Self::KeepFreedMemory,
        }
    }

    /// glibc's variables for this tuning. Setting either threshold turns off glibc's moving
    /// ones, so the tasks set both: the mmap threshold alone would stay at 128 KiB.
    #[cfg_attr(not(all(target_os = "linux", target_env = "gnu")), allow(dead_code))]
    fn environment(self) -> &'static [(&'static str, usize)] {
        const MMAP: &str = "MALLOC_MMAP_THRESHOLD_";
        const TRIM: &str = "MALLOC_TRIM_THRESHOLD_";
        match self {
            Self::ReturnLargeBlocks => &[(MMAP, EVALUATE_MMAP_THRESHOLD)],
            Self::KeepFreedMemory => &[(MMAP, TASK_MMAP_THRESHOLD), (TRIM, TASK_TRIM_THRESHOLD)],
        }
    }
}

/// The error and its causes joined by ": ", leaving out a cause whose text the message already
/// carries (many library errors put their source into their own message).
fn error_chain(e: &anyhow::Error) -> String {
    let mut out = e.to_string();
    for cause in e.chain().skip(1) {
        let text = cause.to_string();
        if !out.contains(&text) {
            out.push_str(": ");
            out.push_str(&text);
        }
    }
    out
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum LogFormat {
    Text,
    Json,
}

fn real_main(cli: Cli) -> Result<()> {
    let logs = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_env("PRECIMAP_LOG").unwrap_or_else(|_| "warn".into()))
        .with_writer(std::io::stderr);
    match cli.log_format {
        LogFormat::Text => logs.init(),
        LogFormat::Json => logs.json().with_current_span(true).with_span_list(false).init(),
    }
    if let Some(n) = cli.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global().context("setting up the thread pool")?;
    }
    match cli.command {
        Command::Simulate {
            scale,
            seed,
            out,
            laz,
            field,
            points_per_revolution,
            revolutions_per_s,
            config,
            scene,
            errors,
            passes,
            heads,
            multibeam,
            rings,
            firings_per_revolution,
            control,
        } => {
            let mut config = match config {
                Some(path) => {
                    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
                    serde_json::from_str(&text)
                        .with_context(|| format!("{}: not a simulation config", path.display()))?
                }
                None => precimap_sim::SimConfig::for_scale(scale, seed),
            };
            if let Some(p) = passes {
                config.drive.passes = p;
                config.drive.stop_pass = config.drive.stop_pass.filter(|&s| s < p);
                config.errors.outage_pass = config.errors.outage_pass.filter(|&s| s < p);
            }
            if let Some(h) = heads {
                config.scanner.heads = h;
            }
            if let Some(s) = scene {
                s.apply(&mut config);
            }
            if let Some(e) = errors {
                e.apply(&mut config);
            }
            if let Some(n) = points_per_revolution {
                config.scanner.points_per_revolution = n;
            }
            if let Some(r) = revolutions_per_s {
                config.scanner.revolutions_per_s = r;
            }
            if multibeam {
                let mut mb = config.scanner.multibeam.take().unwrap_or_default();
                mb.rings = rings.unwrap_or(mb.rings);
                mb.firings_per_revolution = firings_per_revolution.unwrap_or(mb.firings_per_revolution);
                mb.revolutions_per_s = revolutions_per_s.unwrap_or(mb.revolutions_per_s);
                config.scanner.multibeam = Some(mb);
            }
            control.apply(&mut config)?;
            simulate(&config, &out, laz)?;
            if field {
                let dir = out.join("field");
                let week = precimap_sim::field::write_field_campaign(&out, &dir, config.origin, laz)
                    .with_context(|| format!("writing the field campaign into {}", dir.display()))?;
                eprintln!("  field campaign (SBET + UTM 32N strips, GPS week {week}): {}", dir.display());
            }
            Ok(())
        }
        Command::Run { manifest, out, keep_work, in_process, assignments } => {
            if in_process {
                run(&manifest, &out, keep_work, assignments).map(|_| ())
            } else {
                service::run_framework(&manifest, &out, keep_work).map(|_| ())
            }
        }
        Command::Serve(args) => service::serve(args),
        Command::Work(args) => {
            let code = service::work(args)?;
            if code != 0 {
                std::process::exit(code);
            }
            Ok(())
        }
        Command::Submit { manifest, client } => service::submit(&manifest, &client),
        Command::Status { id, watch, json, client } => {
            let code = service::status(id, watch, json, &client)?;
            if code != 0 {
                std::process::exit(code);
            }
            Ok(())
        }
        Command::Results { id, out, client } => service::results(id, &out, &client),
        Command::Cancel { id, client } => service::cancel(id, &client),
        Command::Delete { id, client } => service::delete(id, &client),
        Command::Evaluate { truth, result, json } => evaluate(&truth, &result, json),
        Command::Parameters { manifest } => {
            let parameters = match manifest {
                Some(path) => precimap_formats::manifest::load_manifest(&path)?.parameters,
                None => precimap_core::Parameters::default(),
            };
            println!("{}", serde_json::to_string_pretty(&parameters)?);
            Ok(())
        }
        Command::Demo { scale, seed, out } => {
            let campaign = out.join("campaign");
            let result = out.join("result");
            simulate(&precimap_sim::SimConfig::for_scale(scale, seed), &campaign, false)?;
            service::run_framework(&campaign.join("manifest.json"), &result, false)?;
            evaluate(&campaign.join("truth"), &result, false)?;
            eprintln!(
                "\ncorrected strips and trajectories: {}\nlatent map (LAS, one file per tile): {}\nreport: {}\n\
                 QC plots (SVG, open in a browser): {}",
                result.display(),
                result.join("latent").display(),
                result.join("report.json").display(),
                result.join(precimap_pipeline::qc::QC_DIR).display()
            );
            Ok(())
        }
        Command::Segments(args) => segments::run(args),
        Command::Bench { what } => bench::run(what),
    }
}

/// `simulate`'s ground control.
#[derive(clap::Args, Debug)]
struct ControlArgs {
    /// Survey ground control: a road marking's corner and a façade corner every M metres along
    /// the driven streets as control targets, the same midway between them as check targets; the
    /// manifest states them (`control`, in the grid with `--field`), the truth knows them.
    #[arg(long, value_name = "M")]
    control_spacing: Option<f64>,
    /// The survey's σ in metres, one for every axis or x,y,z (with control; default 0.005).
    #[arg(long, value_name = "S", value_delimiter = ',')]
    control_sigma: Vec<f64>,
    /// Check targets every M metres along the streets instead of midway between control targets.
    #[arg(long, value_name = "M")]
    check_spacing: Option<f64>,
}

impl ControlArgs {
    /// Sets the control of `config`; any of the options turns it on.
    fn apply(&self, config: &mut precimap_sim::SimConfig) -> Result<()> {
        if self.control_spacing.is_none() && self.control_sigma.is_empty() && self.check_spacing.is_none() {
            return Ok(());
        }
        let control = config.control.get_or_insert_with(Default::default);
        if let Some(m) = self.control_spacing {
            control.spacing_m = m;
        }
        control.sigma_m = match self.control_sigma[..] {
            [] => control.sigma_m,
            [s] => precimap_formats::manifest::Sigma::All(s),
            [x, y, z] => precimap_formats::manifest::Sigma::PerAxis([x, y, z]),
            _ => anyhow::bail!("--control-sigma takes one number or three (x,y,z), got {:?}", self.control_sigma),
        };
        if self.check_spacing.is_some() {
            control.check_spacing_m = self.check_spacing;
        }
        Ok(())
    }
}

fn simulate(config: &precimap_sim::SimConfig, out: &std::path::Path, laz: bool) -> Result<()> {
    let started = std::time::Instant::now();
    eprintln!("simulating a {:?} campaign (seed {}) into {}", config.scale, config.seed, out.display());
    let summary =
        precimap_sim::simulate(config, out, laz).with_context(|| format!("simulating into {}", out.display()))?;
    eprintln!(
        "  {} points in {} strips of {} trajectories ({:.1} s)",
        summary.points,
        summary.strips,
        summary.trajectories,
        started.elapsed().as_secs_f64()
    );
    if config.control.is_some() {
        let c = &summary.control_targets;
        eprintln!(
            "  targets (road marking + façade corner): control {} + {}, check {} + {}",
            c.control_road, c.control_facade, c.check_road, c.check_facade
        );
    }
    Ok(())
}

fn run(
    manifest: &std::path::Path,
    out: &std::path::Path,
    keep_work: bool,
    assignments: bool,
) -> Result<precimap_pipeline::Report> {
    let options = precimap_pipeline::RunOptions { out_dir: out.to_path_buf(), keep_work, assignments };
    let display = progress::Display::new();
    let report = precimap_pipeline::run_campaign(manifest, &options, &|p| display.show(p))
        .with_context(|| format!("running {}", manifest.display()))?;
    display.finish(&report);
    Ok(report)
}

fn evaluate(truth: &std::path::Path, result: &std::path::Path, json: bool) -> Result<()> {
    let converted = field_result_in_frame(truth, result)?;
    let result_in_frame = converted.as_ref().map_or(result, |d| d.path());
    let evaluation = precimap_eval::evaluate(truth, result_in_frame)
        .with_context(|| format!("evaluating {} against {}", result.display(), truth.display()))?;
    if json {
        outln!("{}", serde_json::to_string_pretty(&evaluation)?);
    } else {
        outln!("{}", evaluation.summary());
    }
    Ok(())
}

/// The result of a simulated field campaign (`simulate --field`: its trajectories have a `.prj`)
/// mapped back into the simulation's frame, where the truth is; `None` for any other result.
fn field_result_in_frame(truth: &std::path::Path, result: &std::path::Path) -> Result<Option<tempfile::TempDir>> {
    let trajectories = std::fs::read_dir(result.join("trajectories")).into_iter().flatten().flatten();
    if !trajectories.into_iter().any(|e| e.path().extension().is_some_and(|x| x == "prj")) {
        return Ok(None);
    }
    let file = [truth.join("truth.json"), truth.join("truth").join("truth.json")]
        .into_iter()
        .find(|p| p.is_file())
        .with_context(|| format!("{}: no truth.json of a simulated campaign", truth.display()))?;
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&file).with_context(|| file.display().to_string())?)
            .with_context(|| format!("{}: not JSON", file.display()))?;
    let origin: Option<Vec<f64>> = v["origin"].as_array().map(|a| a.iter().filter_map(|x| x.as_f64()).collect());
    let start = v["trajectories"][0]["start_time"].as_f64();
    let (Some([e, n, h]), Some(week)) = (
        origin.and_then(|o| <[f64; 3]>::try_from(o).ok()),
        start.and_then(precimap_formats::gps_time::week_of_adjusted),
    ) else {
        anyhow::bail!("{}: no origin or start time; simulate the campaign again", file.display());
    };
    let dir = tempfile::tempdir().context("creating a temporary folder for the field result in the frame")?;
    precimap_sim::field::result_to_local(result, dir.path(), [e, n, h], week)
        .with_context(|| format!("{}: mapping the field result into the simulation's frame", result.display()))?;
    Ok(Some(dir))
}

#[cfg(test)]
mod tests {
    use super::{Cli, MallocTuning};
    use clap::Parser;

    #[test]
    fn the_subcommand_is_found_past_global_options() {
        let tuning = |a: &[&str]| {
            Cli::try_parse_from(std::iter::once("precimap").chain(a.iter().copied())).ok().map(|c| MallocTuning::of(&c))
        };
        let evaluate = Some(MallocTuning::ReturnLargeBlocks);
        assert_eq!(tuning(&["evaluate", "--truth", "t", "--result", "r"]), evaluate);
        assert_eq!(tuning(&["--threads", "2", "evaluate", "--truth", "t", "--result", "r"]), evaluate);
        assert_eq!(tuning(&["--threads=2", "run", "m.json", "--out", "o"]), Some(MallocTuning::KeepFreedMemory));
        assert_eq!(tuning(&["--help"]), None);
        assert_eq!(tuning(&[]), None);
    }
}
