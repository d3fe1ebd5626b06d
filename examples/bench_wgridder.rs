//! `cargo run --release --example bench_wgridder -- --visibilities 1000000 --size 1024
//! --fov 15 --epsilon 1e-5 --threads 1 [--w-factor 1] [--oversampling 0 (0: suggested)] [--repeats 3]
//! [--seed 1]`: the w-gridding benchmark (`r2d2 bench wgridder`) as JSON.

use r2d2_imaging::bench::{run_wgridder_bench, WGridderBenchParams};

fn main() {
    let mut p = WGridderBenchParams::default();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut i = 0;
    while i < args.len() {
        let value = args.get(i + 1).unwrap_or_else(|| fail(&format!("{} needs a value", args[i])));
        match args[i].as_str() {
            "--visibilities" => p.visibilities = parse(&args[i], value),
            "--size" => p.size = parse(&args[i], value),
            "--fov" => p.fov_deg = parse(&args[i], value),
            "--w-factor" => p.w_factor = parse(&args[i], value),
            "--epsilon" => p.epsilon = parse(&args[i], value),
            "--oversampling" => p.oversampling = parse(&args[i], value),
            "--threads" => p.threads = parse(&args[i], value),
            "--repeats" => p.repeats = parse(&args[i], value),
            "--seed" => p.seed = parse(&args[i], value),
            other => fail(&format!("unknown option {other}")),
        }
        i += 2;
    }
    match run_wgridder_bench(&p) {
        Ok(report) => println!("{}", serde_json::to_string_pretty(&report).expect("report serialises")),
        Err(e) => fail(&e.to_string()),
    }
}

fn parse<T: std::str::FromStr>(flag: &str, value: &str) -> T {
    value.parse().unwrap_or_else(|_| fail(&format!("cannot parse {flag} {value}")))
}

fn fail(msg: &str) -> ! {
    eprintln!("bench_wgridder: {msg}");
    std::process::exit(2)
}
