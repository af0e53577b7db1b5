//! Success-rate files and their agreement (`bridgev2w eval-policy`): the
//! real-robot and the world-model success rates of the same tasks and
//! policies, read from JSON (`{"task": {"policy": rate}}`) or CSV
//! (`task,policy,success_rate`), compared per task with [`mmrv`] and
//! [`pearson`] and averaged over tasks.

use crate::ranking::{mmrv, pearson};
use crate::MetricError;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Errors of reading and comparing success rates; each names the file,
/// the task or policy, and what was expected.
#[derive(Debug, thiserror::Error)]
pub enum RatesError {
    /// The file could not be read.
    #[error("reading {}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A CSV line that is not `task,policy,success_rate`.
    #[error("{}, line {line}: {message}", path.display())]
    Line {
        /// The file.
        path: PathBuf,
        /// The 1-based line number.
        line: usize,
        /// What was found and what was expected.
        message: String,
    },
    /// Not JSON of the expected shape.
    #[error("{}: expected JSON {{\"task\": {{\"policy\": success_rate}}}}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// Where and why.
        source: serde_json::Error,
    },
    /// A success rate outside `[0, 1]` (or not finite).
    #[error("{}: task \"{task}\", policy \"{policy}\": success rate {rate} is outside [0, 1]", path.display())]
    OutOfRange {
        /// The file.
        path: PathBuf,
        /// The task.
        task: String,
        /// The policy.
        policy: String,
        /// The rate.
        rate: f64,
    },
    /// A file without any success rate.
    #[error("{}: no success rates", path.display())]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// A task in one file only.
    #[error("task \"{task}\" is in {} but not in {}", present.display(), absent.display())]
    MissingTask {
        /// The task.
        task: String,
        /// The file that has it.
        present: PathBuf,
        /// The file that lacks it.
        absent: PathBuf,
    },
    /// A task whose policies differ between the two files.
    #[error("task \"{task}\": policies differ between {} ({real_policies:?}) and {} ({sim_policies:?})", real.display(), sim.display())]
    PolicyMismatch {
        /// The task.
        task: String,
        /// The real-robot file.
        real: PathBuf,
        /// Its policies of the task.
        real_policies: Vec<String>,
        /// The world-model file.
        sim: PathBuf,
        /// Its policies of the task.
        sim_policies: Vec<String>,
    },
    /// From the ranking metrics.
    #[error(transparent)]
    Metric(#[from] MetricError),
}

/// Result of this module.
pub type Result<T> = std::result::Result<T, RatesError>;

/// Success rates per task and policy, with the file they came from (named
/// in errors).
#[derive(Debug, Clone, PartialEq)]
pub struct Rates {
    /// The file (or another label of the source).
    pub source: PathBuf,
    /// Success rate in `[0, 1]` per task, then per policy.
    pub tasks: BTreeMap<String, BTreeMap<String, f64>>,
}

impl Rates {
    /// Rates from `source`, checked: every rate finite and in `[0, 1]`, at
    /// least one rate.
    pub fn new(
        source: impl Into<PathBuf>,
        tasks: BTreeMap<String, BTreeMap<String, f64>>,
    ) -> Result<Self> {
        let source = source.into();
        for (task, policies) in &tasks {
            for (policy, &rate) in policies {
                if !(rate.is_finite() && (0.0..=1.0).contains(&rate)) {
                    return Err(RatesError::OutOfRange {
                        path: source,
                        task: task.clone(),
                        policy: policy.clone(),
                        rate,
                    });
                }
            }
        }
        if tasks.is_empty() {
            return Err(RatesError::Empty { path: source });
        }
        Ok(Self { source, tasks })
    }
}

/// Reads a success-rate file: CSV (`.csv`: `task,policy,success_rate` per
/// line, an optional header line starting with `task`) or JSON (any other
/// extension: `{"task": {"policy": rate}}`).
pub fn read_rates(path: &Path) -> Result<Rates> {
    let text = std::fs::read_to_string(path).map_err(|source| RatesError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let tasks = if path
        .extension()
        .is_some_and(|x| x.eq_ignore_ascii_case("csv"))
    {
        parse_csv(path, &text)?
    } else {
        serde_json::from_str(&text).map_err(|source| RatesError::Json {
            path: path.to_path_buf(),
            source,
        })?
    };
    Rates::new(path, tasks)
}

/// The rates of CSV `text` (from `path`, named in errors).
fn parse_csv(path: &Path, text: &str) -> Result<BTreeMap<String, BTreeMap<String, f64>>> {
    let mut tasks: BTreeMap<String, BTreeMap<String, f64>> = BTreeMap::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || (i == 0 && line.to_ascii_lowercase().starts_with("task")) {
            continue;
        }
        let bad = |message: String| RatesError::Line {
            path: path.to_path_buf(),
            line: i + 1,
            message,
        };
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        let [task, policy, rate] = f[..] else {
            return Err(bad(format!(
                "expected task,policy,success_rate, got \"{line}\""
            )));
        };
        let rate: f64 = rate
            .parse()
            .map_err(|_| bad(format!("success rate \"{rate}\" is not a number")))?;
        tasks
            .entry(task.into())
            .or_default()
            .insert(policy.into(), rate);
    }
    Ok(tasks)
}

/// The agreement of one task's world-model success rates with the real ones.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskAgreement {
    /// The task.
    pub task: String,
    /// Mean Maximum Rank Violation (lower is better).
    pub mmrv: f64,
    /// Pearson r (higher is better).
    pub pearson: f64,
}

/// The agreement of world-model success rates with real ones, per task (in
/// task-name order) and averaged over tasks.
#[derive(Debug, Clone, PartialEq)]
pub struct PolicyAgreement {
    /// Per task.
    pub tasks: Vec<TaskAgreement>,
    /// MMRV averaged over tasks.
    pub mean_mmrv: f64,
    /// Pearson r averaged over tasks.
    pub mean_pearson: f64,
}

impl PolicyAgreement {
    /// The markdown table: a row per task, then the average (3 decimals).
    pub fn markdown(&self) -> String {
        let mut text = String::from("| Tasks | MMRV | Pearson r |\n|---|---|---|\n");
        for t in &self.tasks {
            text.push_str(&format!(
                "| {} | {:.3} | {:.3} |\n",
                t.task, t.mmrv, t.pearson
            ));
        }
        text.push_str(&format!(
            "| Avg. | {:.3} | {:.3} |\n",
            self.mean_mmrv, self.mean_pearson
        ));
        text
    }

    /// `{"tasks": {"TASK": {"mmrv": .., "pearson": ..}}, "average": {"mmrv": .., "pearson": ..}}`.
    pub fn to_json(&self) -> serde_json::Value {
        let tasks: serde_json::Map<String, serde_json::Value> = self
            .tasks
            .iter()
            .map(|t| {
                (
                    t.task.clone(),
                    serde_json::json!({"mmrv": t.mmrv, "pearson": t.pearson}),
                )
            })
            .collect();
        serde_json::json!({
            "tasks": tasks,
            "average": {"mmrv": self.mean_mmrv, "pearson": self.mean_pearson},
        })
    }
}

/// Compares world-model rates `sim` with real-robot rates `real`: both must
/// hold the same tasks, and each task the same policies.
pub fn compare(real: &Rates, sim: &Rates) -> Result<PolicyAgreement> {
    let mut tasks = Vec::new();
    for (task, real_p) in &real.tasks {
        let Some(sim_p) = sim.tasks.get(task) else {
            return Err(RatesError::MissingTask {
                task: task.clone(),
                present: real.source.clone(),
                absent: sim.source.clone(),
            });
        };
        if !sim_p.keys().eq(real_p.keys()) {
            return Err(RatesError::PolicyMismatch {
                task: task.clone(),
                real: real.source.clone(),
                real_policies: real_p.keys().cloned().collect(),
                sim: sim.source.clone(),
                sim_policies: sim_p.keys().cloned().collect(),
            });
        }
        let r: Vec<f64> = real_p.values().copied().collect();
        let s: Vec<f64> = sim_p.values().copied().collect();
        tasks.push(TaskAgreement {
            task: task.clone(),
            mmrv: mmrv(&s, &r)?,
            pearson: pearson(&s, &r)?,
        });
    }
    if let Some(task) = sim.tasks.keys().find(|t| !real.tasks.contains_key(*t)) {
        return Err(RatesError::MissingTask {
            task: task.clone(),
            present: sim.source.clone(),
            absent: real.source.clone(),
        });
    }
    let n = tasks.len() as f64;
    Ok(PolicyAgreement {
        mean_mmrv: tasks.iter().map(|t| t.mmrv).sum::<f64>() / n,
        mean_pearson: tasks.iter().map(|t| t.pearson).sum::<f64>() / n,
        tasks,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn rates(source: &str, rows: &[(&str, &str, f64)]) -> Rates {
        let mut tasks: BTreeMap<String, BTreeMap<String, f64>> = BTreeMap::new();
        for (t, p, r) in rows {
            tasks
                .entry((*t).into())
                .or_default()
                .insert((*p).into(), *r);
        }
        Rates::new(source, tasks).unwrap()
    }

    #[test]
    fn csv_and_json_read_alike_and_errors_name_file_and_line() {
        let dir = tempfile::tempdir().unwrap();
        let tmp = dir.path();
        let csv = tmp.join("r.csv");
        std::fs::write(
            &csv,
            "task,policy,success_rate\npush,p1,0.5\n\npush,p2,0.25\n",
        )
        .unwrap();
        let json = tmp.join("r.json");
        std::fs::write(&json, r#"{"push": {"p1": 0.5, "p2": 0.25}}"#).unwrap();
        assert_eq!(
            read_rates(&csv).unwrap().tasks,
            read_rates(&json).unwrap().tasks
        );
        std::fs::write(&csv, "push,p1\n").unwrap();
        let e = read_rates(&csv).unwrap_err().to_string();
        assert!(
            e.contains("r.csv, line 1: expected task,policy,success_rate"),
            "{e}"
        );
        std::fs::write(&csv, "push,p1,high\n").unwrap();
        let e = read_rates(&csv).unwrap_err().to_string();
        assert!(e.contains("success rate \"high\" is not a number"), "{e}");
        std::fs::write(&json, "[1]").unwrap();
        let e = read_rates(&json).unwrap_err().to_string();
        assert!(e.contains("r.json: expected JSON"), "{e}");
        std::fs::write(&csv, "task\n").unwrap();
        let e = read_rates(&csv).unwrap_err().to_string();
        assert!(e.contains("no success rates"), "{e}");
    }

    #[test]
    fn compare_averages_tasks_and_names_mismatches() {
        let real = rates(
            "real.json",
            &[
                ("push", "a", 0.2),
                ("push", "b", 0.6),
                ("pick", "a", 0.1),
                ("pick", "b", 0.5),
            ],
        );
        let sim = rates(
            "sim.csv",
            &[
                ("push", "a", 0.6),
                ("push", "b", 0.2),
                ("pick", "a", 0.2),
                ("pick", "b", 0.6),
            ],
        );
        let a = compare(&real, &sim).unwrap();
        assert_eq!(a.tasks[0].task, "pick");
        assert_eq!(a.tasks[0].mmrv, 0.0);
        assert!((a.tasks[1].mmrv - 0.4).abs() < 1e-12);
        assert!((a.mean_mmrv - 0.2).abs() < 1e-12);
        let md = a.markdown();
        assert!(md.contains("| pick | 0.000 | 1.000 |"), "{md}");
        assert!(
            md.contains("| push | 0.400 | -1.000 |\n| Avg. | 0.200 |"),
            "{md}"
        );
        assert!((a.to_json()["average"]["mmrv"].as_f64().unwrap() - 0.2).abs() < 1e-12);
        let other = rates("sim.csv", &[("push", "a", 0.6), ("push", "c", 0.2)]);
        let e = compare(&real, &other).unwrap_err().to_string();
        assert!(
            e.contains("task \"pick\" is in real.json but not in sim.csv"),
            "{e}"
        );
        let e = compare(&other, &real).unwrap_err().to_string();
        assert!(
            e.contains("task \"push\": policies differ between sim.csv"),
            "{e}"
        );
        let e = Rates::new(
            "x.csv",
            [("t".to_string(), [("p".to_string(), 1.5)].into())].into(),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("x.csv: task \"t\", policy \"p\": success rate 1.5 is outside [0, 1]"),
            "{e}"
        );
    }
}
