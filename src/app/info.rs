//! `vscatter info`: what `vdb_print -l` tells a user, for every grid of a VDB file — as text for
//! people or JSON for scripts and tests.

use std::io::Write;

use serde_json::{json, Value};

use super::args::InfoArgs;
use vscatter::error::{Error, Result};
use vscatter::volume::vdb::{ValueKind, VdbFile};

/// Runs `vscatter info`: a `.vtc` cache (recognised by its magic) or a VDB file.
pub fn run(args: &InfoArgs) -> Result<()> {
    if vscatter::transfer::cache::is_cache(&args.file)? {
        return cache_info(args);
    }
    let vdb = VdbFile::open(&args.file)?;
    let chosen = match &args.grid {
        Some(name) => vec![vdb.choose_grid(Some(name))?],
        None => (0..vdb.grids.len()).collect(),
    };
    let mut grids = Vec::new();
    for i in chosen {
        let g = &vdb.grids[i];
        let tree = match g.kind {
            ValueKind::Readable { .. } => Some(vdb.read_grid(i)?),
            ValueKind::Unsupported => None,
        };
        grids.push(g.describe(tree.as_ref()));
    }
    let report = json!({
        "file": args.file.display().to_string(),
        "format_version": vdb.version,
        "library_version": format!("{}.{}", vdb.library.0, vdb.library.1),
        "grids": grids,
    });
    let text = if args.json {
        format!("{report:#}\n")
    } else {
        render_text(&report)
    };
    std::io::stdout()
        .lock()
        .write_all(text.as_bytes())
        .map_err(|e| Error::io("<stdout>", e))
}

/// Describes a transfer cache: its header, once the whole file's checksum has been verified (a
/// damaged cache is reported as damaged, not described).
fn cache_info(args: &InfoArgs) -> Result<()> {
    let h = vscatter::transfer::cache::verify(&args.file)?;
    let size = std::fs::metadata(&args.file)
        .map_err(|e| Error::io(&args.file, e))?
        .len();
    let text = if args.json {
        let mut v = serde_json::to_value(&h).map_err(|e| Error::Runtime(e.to_string()))?;
        v["file"] = json!(args.file.display().to_string());
        v["file_bytes"] = json!(size);
        v["format_version"] = json!(vscatter::transfer::cache::VERSION);
        format!("{v:#}\n")
    } else {
        h.describe(&args.file, size)
    };
    std::io::stdout()
        .lock()
        .write_all(text.as_bytes())
        .map_err(|e| Error::io("<stdout>", e))
}

fn vec3(v: &Value) -> String {
    match v.as_array() {
        Some(a) => {
            let parts: Vec<String> = a.iter().map(|x| x.to_string()).collect();
            format!("({})", parts.join(", "))
        }
        None => "-".into(),
    }
}

fn render_text(r: &Value) -> String {
    let grids = r["grids"].as_array().map_or(&[][..], |g| g.as_slice());
    let mut out = format!(
        "{}: OpenVDB file format {} (library {}), {} grid{}\n",
        r["file"].as_str().unwrap_or_default(),
        r["format_version"],
        r["library_version"].as_str().unwrap_or_default(),
        grids.len(),
        if grids.len() == 1 { "" } else { "s" }
    );
    for g in grids {
        let s = |k: &str| g[k].as_str().unwrap_or("-").to_string();
        let half = if g["half"].as_bool() == Some(true) {
            " (half)"
        } else {
            ""
        };
        out += &format!(
            "\n{}  {}{}  {}  [{}]\n",
            s("name"),
            s("value_type"),
            half,
            s("class"),
            s("compression")
        );
        if let Some(p) = g["instance_of"].as_str() {
            out += &format!("  instance of {p}\n");
        }
        out += &format!(
            "  transform   {}, voxel size {}, translation {}\n",
            s("map_type"),
            vec3(&g["voxel_size"]),
            vec3(&g["translation"])
        );
        if let Some(note) = g["note"].as_str() {
            out += &format!("  {note}\n");
            continue;
        }
        match (g["bbox_min"].as_array(), g["bbox_max"].as_array()) {
            (Some(lo), Some(hi)) => {
                let dims: Vec<String> = lo
                    .iter()
                    .zip(hi)
                    .map(|(a, b)| {
                        (b.as_i64().unwrap_or(0) - a.as_i64().unwrap_or(0) + 1).to_string()
                    })
                    .collect();
                out += &format!(
                    "  bbox        {} -> {}  ({} voxels)\n",
                    vec3(&g["bbox_min"]),
                    vec3(&g["bbox_max"]),
                    dims.join(" x ")
                );
            }
            _ => out += "  bbox        empty\n",
        }
        out += &format!(
            "  active      {} voxels in {} leaves and {} tiles\n",
            g["active_voxels"], g["leaves"], g["tiles"]
        );
        if !g["value_min"].is_null() {
            out += &format!(
                "  {:<11} {} .. {}",
                if s("value_range_of") == "values" {
                    "values"
                } else {
                    "|vectors|"
                },
                g["value_min"],
                g["value_max"]
            );
            if !g["value_sum"].is_null() {
                out += &format!("  (sum {})", g["value_sum"]);
            }
            out += "\n";
        }
        out += &format!(
            "  memory      {}\n",
            indicatif::HumanBytes(g["memory_bytes"].as_u64().unwrap_or(0))
        );
    }
    out
}
