use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use burn::tensor::Tensor;
use clap::{Args, Parser, Subcommand};

use acags::bench::{RASTER_CASES, bench_raster};
use acags::compute_backend::{BackendKind, resolve};
use acags::data::synthetic::{SyntheticPreset, write_dataset};
use acags::data::{DatasetLayout, LoadOptions};
use acags::io::{
    camera_json::read_camera,
    image_out::write_render,
    splat_ply::{read_splat_ply, render_splat},
};
use acags::run::SceneLocation;

#[derive(Parser)]
#[command(
    name = "acags",
    version,
    about = "Adaptive-capacity anchored Gaussian splatting for dynamic scenes"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// What `eval` and `render` read: a run directory, or a `scene.acags` file (and its dataset).
#[derive(Args)]
struct SceneSource {
    /// A run directory written by `acags train`.
    #[arg(
        long,
        required_unless_present = "bitstream",
        conflicts_with = "bitstream"
    )]
    run: Option<PathBuf>,
    /// A scene.acags file written by `acags compress`, instead of a run.
    #[arg(long)]
    bitstream: Option<PathBuf>,
    /// Dataset for --bitstream (default: the one in the file's embedded config).
    #[arg(long, requires = "bitstream")]
    data: Option<String>,
}

impl SceneSource {
    fn resolve(self) -> Result<SceneLocation> {
        match (self.run, self.bitstream) {
            (_, Some(file)) => Ok(SceneLocation::Bitstream {
                file,
                data: self.data,
            }),
            (Some(run), None) => Ok(SceneLocation::Run(run)),
            (None, None) => bail!("give --run DIR or --bitstream FILE"),
        }
    }
}

#[derive(Subcommand)]
enum Command {
    /// Render a standard 3DGS PLY from a camera (PNG, or float32 .npy H x W x 4 with alpha).
    RenderPly {
        #[arg(long)]
        ply: PathBuf,
        /// JSON: width, height, fx, fy, cx, cy, world_to_camera (4x4 row-major, OpenCV axes).
        #[arg(long)]
        camera: PathBuf,
        #[arg(long)]
        out: PathBuf,
        #[arg(long, value_enum, default_value = "auto")]
        backend: BackendKind,
        /// Background colour "r,g,b" in [0, 1].
        #[arg(long, default_value = "0,0,0", value_parser = parse_rgb)]
        background: [f32; 3],
    },
    /// Train a model (GIFStream baseline); with no arguments, on the embedded synthetic scene.
    Train(acags::run::TrainOptions),
    /// Recompute a run's test metrics (writes metrics.json and renders/), or a bitstream's
    /// (writes <stem>_metrics.json and <stem>_renders/ beside the file).
    Eval {
        #[command(flatten)]
        source: SceneSource,
        #[arg(long, value_enum, default_value = "auto")]
        backend: BackendKind,
    },
    /// PSNR, SSIM, LPIPS-Alex and LPIPS-VGG (when its weights are present) of one pair of 8-bit
    /// RGB images (PNG or JPEG) of equal size.
    Metrics {
        a: PathBuf,
        b: PathBuf,
        /// Print JSON instead of one line.
        #[arg(long)]
        json: bool,
        /// LPIPS input convention: `normalized` maps [0, 1] to [-1, 1] (correct); `unscaled`
        /// feeds [0, 1] as GIFStream's evaluator does.
        #[arg(long, value_enum, default_value = "normalized")]
        lpips_input: acags::eval::lpips::LpipsInput,
        /// LPIPS-VGG: `auto` when its weights are present, `on` (missing weights are an error), `off`.
        #[arg(long, value_enum, default_value = "auto")]
        vgg: acags::eval::config::VggLpips,
        #[arg(long, value_enum, default_value = "ndarray")]
        backend: BackendKind,
    },
    /// Quantise and entropy-code a trained run into one file (default RUN/scene.acags) and
    /// print the size of every section.
    Compress {
        #[arg(long)]
        run: PathBuf,
        #[arg(long)]
        out: Option<PathBuf>,
        /// Rate preset (default: the one the run trained with; another one rounds a model that
        /// never saw that grid).
        #[arg(long, value_enum)]
        rate: Option<acags::codec::quantization::RatePreset>,
    },
    /// Render a trained run from one of its cameras over a frame range (PNG frames, and an mp4
    /// when ffmpeg is installed).
    Render {
        #[command(flatten)]
        source: SceneSource,
        /// Camera index in the dataset's sorted camera list.
        #[arg(long)]
        camera: usize,
        /// Frames A..B (end exclusive) or a single frame.
        #[arg(long, value_parser = acags::run::parse_frame_range)]
        frames: std::ops::Range<usize>,
        /// Output directory (default RUN/render_camII).
        #[arg(long)]
        out: Option<PathBuf>,
        #[arg(long, value_enum, default_value = "auto")]
        backend: BackendKind,
    },
    /// Export frames of a run or a bitstream as standard 3DGS PLY files (Inria layout: readable by
    /// `render-ply` and common splat viewers), with the rig's cameras and a manifest (export.json).
    Export {
        #[command(flatten)]
        source: SceneSource,
        /// Frames A..B (end exclusive) or a single frame (default: the whole trained GOP).
        #[arg(long, value_parser = acags::run::parse_frame_range)]
        frames: Option<std::ops::Range<usize>>,
        /// Degree of the spherical harmonics the colour is distilled into (0-3).
        #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=3))]
        sh_degree: u8,
        /// Output directory (default RUN/export, or <stem>_export beside a bitstream).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Also render every exported frame from the test cameras and report its PSNR against
        /// acags' own render (in export.json).
        #[arg(long)]
        fidelity: bool,
        #[arg(long, value_enum, default_value = "auto")]
        backend: BackendKind,
    },
    /// Play a run or a scene.acags file in the browser: serves a local page with a time slider,
    /// play/pause, frame rate and an orbit camera starting at a test camera (offline: the page
    /// loads nothing but from this server).
    View {
        /// A run directory or a scene.acags file.
        scene: PathBuf,
        /// Dataset for a scene.acags file (default: the one in its embedded config).
        #[arg(long)]
        data: Option<String>,
        /// Port (0: any free port).
        #[arg(long, default_value_t = 7878)]
        port: u16,
        /// Address to listen on. Anything but a loopback address serves the scene to the network.
        #[arg(long, default_value = "127.0.0.1")]
        bind: std::net::IpAddr,
        /// Degree of the spherical harmonics the frames are distilled into (0-3).
        #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=3))]
        sh_degree: u8,
        #[arg(long, value_enum, default_value = "auto")]
        backend: BackendKind,
    },
    /// Capacity heatmaps of a trained run at one camera and frame (ACA-GS Fig. 7): anchors per
    /// pixel, Neural Gaussians per anchor, active feature channels, over the render.
    Visualize {
        #[arg(long)]
        run: PathBuf,
        /// Camera index in the dataset's sorted camera list.
        #[arg(long)]
        camera: usize,
        /// Frame index in the dataset.
        #[arg(long)]
        frame: usize,
        /// Output directory (default RUN/visualize).
        #[arg(long)]
        out: Option<PathBuf>,
        #[arg(long, value_enum, default_value = "auto")]
        backend: BackendKind,
    },
    /// Train every cell of a sweep grid (configs/sweeps/*.toml) one after another; re-running
    /// skips finished cells and resumes interrupted ones. Writes results.csv and report.md.
    Sweep(acags::experiments::sweep::SweepOptions),
    /// Rewrite a sweep directory's results.csv, report.md and charts from its cells.
    Report {
        #[arg(long)]
        sweep: PathBuf,
    },
    /// Train GIFStream and ACA-GS on scenes built to break methods and report quality,
    /// non-finite steps and collapses (exit status 1 when a run collapsed or failed).
    Stability(acags::experiments::stability::StabilityOptions),
    /// Dataset tools: validate and describe a dataset, or generate a synthetic one.
    Dataset {
        #[command(subcommand)]
        what: DatasetCommand,
    },
    /// Config tools.
    Config {
        #[command(subcommand)]
        what: ConfigCommand,
    },
    /// Benchmarks.
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
}

#[derive(Subcommand)]
enum ConfigCommand {
    /// Print the fully resolved config as TOML: its `extends` chain merged, every default
    /// filled in and the --set overrides applied (what `train` would run and save as
    /// RUN/config.toml).
    Show {
        /// TOML config; the embedded configs/default.toml when omitted.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Override one config key, e.g. --set train.max_steps=500 (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        overrides: Vec<String>,
    },
}

#[derive(Subcommand)]
enum DatasetCommand {
    /// Validate a dataset and print its cameras, frames, resolution, points, bounds and every
    /// problem found (exit status 1 when there is any).
    Info {
        path: PathBuf,
        /// Layout; detected from the files when omitted (MPEG must be named: it looks like N3DV).
        #[arg(long, value_enum)]
        layout: Option<DatasetLayout>,
        #[arg(long, default_value_t = 0)]
        start_frame: usize,
        #[arg(long)]
        frames: Option<usize>,
        #[arg(long, default_value_t = 1)]
        downscale: u32,
        /// Decode every frame completely instead of reading headers only.
        #[arg(long)]
        deep: bool,
    },
    /// Write a procedural dynamic scene in the N3DV layout.
    Synth {
        #[arg(long, value_enum, default_value = "fast")]
        preset: SyntheticPreset,
        #[arg(long)]
        out: PathBuf,
    },
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Seconds per training step of the default (or given) config.
    Train {
        #[arg(long, value_enum, default_value = "auto")]
        backend: BackendKind,
        #[arg(long)]
        config: Option<PathBuf>,
        #[arg(long = "set", value_name = "KEY=VALUE")]
        overrides: Vec<String>,
        /// Untimed steps first (default: through the canonical phase and 2 steps into the
        /// dynamic one, so the timed steps decode the stream and the motion as most of a run
        /// does; 99 with the default 3200 steps).
        #[arg(long)]
        warmup: Option<usize>,
        #[arg(long, default_value_t = 20)]
        steps: usize,
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// LPIPS of one image pair (default: AlexNet at N3DV's 1352x1014): seconds and peak memory.
    Lpips {
        #[arg(long, value_enum, default_value = "ndarray")]
        backend: BackendKind,
        #[arg(long, value_enum, default_value = "alex")]
        net: acags::eval::lpips::LpipsNet,
        #[arg(long, default_value_t = 1352)]
        width: usize,
        #[arg(long, default_value_t = 1014)]
        height: usize,
        /// Timed evaluations after the first (untimed-for-the-median) one.
        #[arg(long, default_value_t = 3)]
        repeats: usize,
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Seconds per rendered test view of a trained run (culling, decoding, rasterizing).
    Render {
        #[arg(long)]
        run: PathBuf,
        #[arg(long, value_enum, default_value = "auto")]
        backend: BackendKind,
        /// Anchor culling to time (default: the run's own).
        #[arg(long, value_enum)]
        culling: Option<acags::model::view::AnchorCulling>,
        /// Timed passes over the test views (after one untimed render).
        #[arg(long, default_value_t = 3)]
        repeats: usize,
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Rasterizer forward and forward+backward on fixed random scenes.
    Raster {
        #[arg(long, value_enum, default_value = "auto")]
        backend: BackendKind,
        /// Write the results as JSON here (they are always printed).
        #[arg(long)]
        json: Option<PathBuf>,
        /// Only the cases whose name contains this.
        #[arg(long)]
        case: Option<String>,
    },
}

/// Prints a report as JSON and also writes it to `path` when given.
fn emit_json(report: &impl serde::Serialize, path: Option<&std::path::Path>) -> Result<()> {
    let text = serde_json::to_string_pretty(report)?;
    println!("{text}");
    if let Some(path) = path {
        std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}

fn parse_rgb(s: &str) -> Result<[f32; 3], String> {
    let parts: Vec<&str> = s.split(',').collect();
    if parts.len() != 3 {
        return Err(format!("expected r,g,b, got '{s}'"));
    }
    let mut rgb = [0.0f32; 3];
    for (v, p) in rgb.iter_mut().zip(parts) {
        *v = p
            .trim()
            .parse()
            .map_err(|_| format!("'{p}' is not a number"))?;
        if !v.is_finite() {
            return Err(format!("'{p}' is not finite"));
        }
    }
    Ok(rgb)
}

fn render_ply(
    ply: PathBuf,
    camera: PathBuf,
    out: PathBuf,
    backend: BackendKind,
    background: [f32; 3],
) -> Result<()> {
    acags::io::image_out::ImageFormat::from_path(&out)?;
    let scene = read_splat_ply(&ply)?;
    let camera = read_camera(&camera)?;
    let chosen = resolve(backend)?;
    eprintln!("backend: {}", chosen.description);
    let n = scene.len();
    let rendered = render_splat(&scene, &camera, background, &chosen.device)?;
    let (h, w) = (camera.height as usize, camera.width as usize);
    let rgba = Tensor::cat(vec![rendered.image, rendered.alpha.reshape([h, w, 1])], 2);
    let rgba: Vec<f32> = rgba
        .into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .context("reading the render")?;
    write_render(&out, &rgba, camera.width, camera.height)?;
    let visible = rendered
        .radii
        .sum_dim(1)
        .greater_elem(0)
        .int()
        .sum()
        .into_scalar::<i64>();
    eprintln!(
        "rendered {n} Gaussians ({visible} visible) at {w}x{h} -> {}",
        out.display()
    );
    Ok(())
}

/// Stack of each worker of rayon's global pool: a CPU training step runs on one
/// (`train.step_thread = "pool"`), with the rate term's graph or another step's work at times
/// on top of it, where it had the main thread's 8 MiB before; rayon's default is 2 MiB.
const POOL_STACK_BYTES: usize = 8 << 20;

fn main() -> Result<()> {
    // Before any parallel work; the thread count stays rayon's (RAYON_NUM_THREADS or the cores).
    rayon::ThreadPoolBuilder::new()
        .stack_size(POOL_STACK_BYTES)
        .build_global()
        .map_err(|e| anyhow::anyhow!("configuring rayon's thread pool: {e}"))?;
    match Cli::parse().command {
        Command::RenderPly {
            ply,
            camera,
            out,
            backend,
            background,
        } => render_ply(ply, camera, out, backend, background),
        Command::Train(options) => acags::run::train(options).map(|_| ()),
        Command::Eval { source, backend } => match source.resolve()? {
            SceneLocation::Bitstream { file, data } => {
                acags::run::eval_bitstream(&file, data.as_deref(), backend).map(|_| ())
            }
            SceneLocation::Run(run) => acags::run::eval(&run, backend).map(|_| ()),
        },
        Command::Sweep(options) => {
            let outcome = acags::experiments::sweep::sweep(&options)?;
            if outcome.failed() > 0 {
                bail!(
                    "{} of {} cells failed (see {})",
                    outcome.failed(),
                    outcome.rows.len(),
                    outcome
                        .dir
                        .join(acags::experiments::report::REPORT_FILE)
                        .display()
                );
            }
            Ok(())
        }
        Command::Report { sweep } => {
            let path = acags::experiments::report::report(&sweep)?;
            println!("{}", path.display());
            Ok(())
        }
        Command::Stability(options) => {
            let report = acags::experiments::stability::stability(&options)?;
            let path = report
                .dir
                .join(acags::experiments::stability::STABILITY_REPORT_FILE);
            println!("{}", std::fs::read_to_string(&path)?);
            let broken = report.broken();
            if !broken.is_empty() {
                bail!(
                    "{} of {} runs are not stable (see {})",
                    broken.len(),
                    report.rows.len(),
                    path.display()
                );
            }
            Ok(())
        }
        Command::Metrics {
            a,
            b,
            json,
            lpips_input,
            vgg,
            backend,
        } => {
            let chosen = resolve(backend)?;
            let config = acags::eval::config::EvalConfig {
                lpips_input,
                lpips_vgg: vgg,
                ..Default::default()
            };
            let metrics = acags::eval::image_pair::pair_metrics(&a, &b, &config, &chosen.device)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&metrics)?);
            } else {
                println!("{}", metrics.text());
            }
            Ok(())
        }
        Command::Compress { run, out, rate } => acags::run::compress(&run, out, rate).map(|_| ()),
        Command::Render {
            source,
            camera,
            frames,
            out,
            backend,
        } => match source.resolve()? {
            SceneLocation::Bitstream { file, data } => {
                acags::run::render_bitstream(&file, data.as_deref(), camera, frames, out, backend)
                    .map(|_| ())
            }
            SceneLocation::Run(run) => {
                acags::run::render(&run, camera, frames, out, backend).map(|_| ())
            }
        },
        Command::Export {
            source,
            frames,
            sh_degree,
            out,
            fidelity,
            backend,
        } => acags::run::export(
            &source.resolve()?,
            frames,
            sh_degree as usize,
            out,
            fidelity,
            backend,
        )
        .map(|_| ()),
        Command::View {
            scene,
            data,
            port,
            bind,
            sh_degree,
            backend,
        } => acags::run::view(
            &SceneLocation::from_path(scene, data)?,
            &acags::view::ViewOptions {
                bind,
                port,
                sh_degree: sh_degree as usize,
            },
            backend,
        ),
        Command::Visualize {
            run,
            camera,
            frame,
            out,
            backend,
        } => acags::run::visualize(&run, camera, frame, out, backend).map(|paths| {
            for p in paths {
                println!("{}", p.display());
            }
        }),
        Command::Config {
            what: ConfigCommand::Show { config, overrides },
        } => {
            let config = acags::train::config::TrainConfig::load(config.as_deref(), &overrides)?;
            print!("{}", config.to_toml());
            Ok(())
        }
        Command::Dataset {
            what:
                DatasetCommand::Info {
                    path,
                    layout,
                    start_frame,
                    frames,
                    downscale,
                    deep,
                },
        } => {
            let options = LoadOptions {
                start_frame,
                frame_count: frames,
                downscale,
                ..Default::default()
            };
            let report = acags::data::inspect::inspect(&path, layout, &options, deep);
            if let Some(summary) = &report.summary {
                print!("{summary}");
            }
            if report.problems.is_empty() {
                println!("problems    none");
                Ok(())
            } else {
                println!("problems    {}", report.problems.len());
                for p in &report.problems {
                    println!("  - {p}");
                }
                std::process::exit(1);
            }
        }
        Command::Dataset {
            what: DatasetCommand::Synth { preset, out },
        } => {
            let start = std::time::Instant::now();
            write_dataset(preset, &out)?;
            eprintln!(
                "wrote synthetic:{} to {} in {:.1} s",
                preset.name(),
                out.display(),
                start.elapsed().as_secs_f64()
            );
            Ok(())
        }
        Command::Bench {
            what:
                BenchCommand::Train {
                    backend,
                    config,
                    overrides,
                    warmup,
                    steps,
                    json,
                },
        } => {
            let chosen = resolve(backend)?;
            eprintln!("backend: {}", chosen.description);
            let config = acags::train::config::TrainConfig::load(config.as_deref(), &overrides)?;
            let warmup = warmup.unwrap_or_else(|| acags::bench::default_train_warmup(&config));
            let report = acags::bench::bench_train(
                &chosen.device,
                &chosen.description,
                &config,
                warmup,
                steps,
            )?;
            emit_json(&report, json.as_deref())
        }
        Command::Bench {
            what:
                BenchCommand::Lpips {
                    backend,
                    net,
                    width,
                    height,
                    repeats,
                    json,
                },
        } => {
            let chosen = resolve(backend)?;
            eprintln!("backend: {}", chosen.description);
            let report = acags::bench::bench_lpips(
                &chosen.device,
                &chosen.description,
                net,
                width,
                height,
                repeats,
            )?;
            emit_json(&report, json.as_deref())
        }
        Command::Bench {
            what:
                BenchCommand::Render {
                    run,
                    backend,
                    culling,
                    repeats,
                    json,
                },
        } => {
            let chosen = resolve(backend)?;
            eprintln!("backend: {}", chosen.description);
            let report = acags::bench::bench_render(
                &chosen.device,
                &chosen.description,
                &run,
                culling,
                repeats,
            )?;
            emit_json(&report, json.as_deref())
        }
        Command::Bench {
            what:
                BenchCommand::Raster {
                    backend,
                    json,
                    case,
                },
        } => {
            let chosen = resolve(backend)?;
            eprintln!("backend: {}", chosen.description);
            let cases: Vec<_> = RASTER_CASES
                .iter()
                .filter(|c| case.as_deref().is_none_or(|f| c.name.contains(f)))
                .copied()
                .collect();
            if cases.is_empty() {
                bail!("no benchmark case matches {case:?}");
            }
            let report = bench_raster(&chosen.device, &chosen.description, &cases)?;
            emit_json(&report, json.as_deref())
        }
    }
}
