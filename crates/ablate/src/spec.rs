//! The ablation file format and its expansion into fully resolved runs.

use crate::AblateError;
use nerf_data::ViewSelection;
use nerf_field::{merge_json, Registry};
use nerf_train::TrainConfig;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The training budget, the same for every run: training stops at whichever limit comes first.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Budget {
    /// Maximum training steps.
    pub iters: Option<u64>,
    /// Maximum training wall time, seconds (evaluation excluded).
    pub seconds: Option<f64>,
}

/// When to evaluate on the test views during training (the final evaluation always happens).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvalSchedule {
    /// Evaluate every this many steps.
    pub every_iters: Option<u64>,
    /// Evaluate every this many seconds of training time.
    pub every_seconds: Option<f64>,
}

/// One explicit run of the file: a name and a `TrainConfig` JSON patch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunSpec {
    /// Name of the run (first part of the run id).
    pub name: String,
    /// `TrainConfig` patch (any key: `field`, `field_config`, `sampler`, …).
    #[serde(default)]
    pub config: Value,
}

fn default_downscale() -> u32 {
    1
}
fn default_seeds() -> Vec<u64> {
    vec![0]
}
fn default_train_views() -> ViewSelection {
    ViewSelection::All
}
fn default_test_views() -> ViewSelection {
    TrainConfig::default().test_views
}

/// An ablation file, as written (see the crate documentation for the format).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AblationSpec {
    /// Name of the ablation (default: the file stem).
    pub name: Option<String>,
    /// Scene folders (any format `nerf train` reads), relative to the file's folder or absolute.
    pub scenes: Vec<PathBuf>,
    /// Image downscale factor.
    #[serde(default = "default_downscale")]
    pub downscale: u32,
    /// Training views.
    #[serde(default = "default_train_views")]
    pub train_views: ViewSelection,
    /// Test views (evaluated at every evaluation point).
    #[serde(default = "default_test_views")]
    pub test_views: ViewSelection,
    /// Seeds; every run is repeated for each.
    #[serde(default = "default_seeds")]
    pub seeds: Vec<u64>,
    /// Training budget of every run.
    pub budget: Budget,
    /// Evaluation points along the way.
    #[serde(default)]
    pub eval: EvalSchedule,
    /// `TrainConfig` patch applied to every run before its own patch.
    #[serde(default)]
    pub base: Value,
    /// Explicit runs.
    #[serde(default)]
    pub runs: Vec<RunSpec>,
    /// Cartesian sweep applied on top of every run: dotted key path into `TrainConfig` → values.
    /// Keys are swept in sorted order, the last key varying fastest.
    #[serde(default)]
    pub grid: BTreeMap<String, Vec<Value>>,
    /// Keep each run's trained fields: `checkpoint.bin` in the run's folder, as `nerf train`
    /// writes it, so that `nerf eval RUN_FOLDER SCENE --test-views …` scores the run on other
    /// views later (e.g. all 200 of lego's on a device that cannot hold them beside the training
    /// views). Not part of the config hash: it changes what is written, not what is trained.
    #[serde(default)]
    pub checkpoints: bool,
}

/// A parsed ablation file together with where it was read from.
#[derive(Clone, Debug)]
pub struct Ablation {
    /// The file.
    pub path: PathBuf,
    /// Its contents.
    pub spec: AblationSpec,
}

/// One fully resolved run of an ablation.
#[derive(Clone, Debug)]
pub struct RunPlan {
    /// Filesystem-safe id: `<run name>[__key=value…]__<scene stem>__s<seed>`.
    pub id: String,
    /// The explicit run's name.
    pub name: String,
    /// Scene folder (resolved against the ablation file's folder).
    pub scene: PathBuf,
    /// Seed.
    pub seed: u64,
    /// The grid point: (dotted key, value) in sweep order.
    pub grid: Vec<(String, Value)>,
    /// The fully resolved training config.
    pub config: TrainConfig,
    /// Stable hash of the config, scene, views and evaluation schedule (16 hex digits).
    pub config_hash: String,
}

impl Ablation {
    /// Reads and checks an ablation file.
    pub fn load(path: &Path) -> Result<Self, AblateError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| AblateError::Read { path: path.to_path_buf(), error: source })?;
        Self::parse(path, &text)
    }

    /// Parses ablation text; `path` is used for relative scene paths and error messages.
    pub fn parse(path: &Path, text: &str) -> Result<Self, AblateError> {
        let spec: AblationSpec = toml::from_str(text)
            .map_err(|e| AblateError::Parse { path: path.to_path_buf(), message: e.to_string().trim().to_string() })?;
        let a = Self { path: path.to_path_buf(), spec };
        a.check()?;
        Ok(a)
    }

    fn invalid(&self, message: impl Into<String>) -> AblateError {
        AblateError::Invalid { path: self.path.clone(), message: message.into() }
    }

    fn check(&self) -> Result<(), AblateError> {
        let s = &self.spec;
        if s.budget.iters.is_none() && s.budget.seconds.is_none() {
            return Err(self.invalid("[budget] needs `iters` and/or `seconds`"));
        }
        if s.budget.iters == Some(0) {
            return Err(self.invalid("budget.iters must be positive"));
        }
        if let Some(t) = s.budget.seconds {
            if !(t.is_finite() && t > 0.0) {
                return Err(self.invalid(format!("budget.seconds must be a positive number, got {t}")));
            }
        }
        if s.eval.every_iters == Some(0) {
            return Err(self.invalid("eval.every_iters must be positive"));
        }
        if let Some(t) = s.eval.every_seconds {
            if !(t.is_finite() && t > 0.0) {
                return Err(self.invalid(format!("eval.every_seconds must be a positive number, got {t}")));
            }
        }
        if s.scenes.is_empty() {
            return Err(self.invalid("`scenes` is empty"));
        }
        if s.seeds.is_empty() {
            return Err(self.invalid("`seeds` is empty"));
        }
        if s.runs.is_empty() {
            return Err(self.invalid("no runs: add at least one [[runs]] entry"));
        }
        if !(s.base.is_null() || s.base.is_object()) {
            return Err(self.invalid("[base] must be a table"));
        }
        for (i, r) in s.runs.iter().enumerate() {
            if r.name.trim().is_empty() {
                return Err(self.invalid(format!("runs[{i}] has an empty name")));
            }
            if s.runs[..i].iter().any(|o| o.name == r.name) {
                return Err(self.invalid(format!("two runs are named `{}`", r.name)));
            }
            if !(r.config.is_null() || r.config.is_object()) {
                return Err(self.invalid(format!("runs `{}`: `config` must be a table", r.name)));
            }
        }
        for (k, v) in &s.grid {
            if v.is_empty() {
                return Err(self.invalid(format!("grid key `{k}` has no values")));
            }
            if k.is_empty() || k.split('.').any(str::is_empty) {
                return Err(self.invalid(format!("grid key `{k}` is not a dotted key path")));
            }
        }
        Ok(())
    }

    /// The ablation's name: `name` from the file, else the file stem.
    pub fn name(&self) -> String {
        self.spec.name.clone().unwrap_or_else(|| {
            self.path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "ablation".into())
        })
    }

    /// Default output folder: `runs/ablate/<name>` (relative to the working directory).
    pub fn default_out_dir(&self) -> PathBuf {
        Path::new("runs").join("ablate").join(safe_name(&self.name()))
    }

    /// Scene `p` resolved against the file's folder.
    pub fn scene_path(&self, p: &Path) -> PathBuf {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            self.path.parent().unwrap_or(Path::new("")).join(p)
        }
    }

    /// All grid points in sweep order (sorted keys, last key fastest); one empty point without a grid.
    pub fn grid_points(&self) -> Vec<Vec<(String, Value)>> {
        let mut points: Vec<Vec<(String, Value)>> = vec![vec![]];
        for (k, values) in &self.spec.grid {
            points = points
                .into_iter()
                .flat_map(|p| {
                    values.iter().map(move |v| {
                        let mut q = p.clone();
                        q.push((k.clone(), v.clone()));
                        q
                    })
                })
                .collect();
        }
        points
    }

    /// Expands the file into runs (runs × grid points × scenes × seeds, in that nesting order)
    /// with fully resolved configs: defaults ← field preset ← `[base]` ← run patch ← grid point,
    /// then the budget, seed, downscale and test views.
    pub fn plan(&self, registry: &Registry) -> Result<Vec<RunPlan>, AblateError> {
        let s = &self.spec;
        let points = self.grid_points();
        // Short id labels: a key's last segment unless two grid keys share it.
        let label = |k: &str| -> String {
            let last = k.rsplit('.').next().unwrap_or(k);
            let clash = s.grid.keys().filter(|o| o.rsplit('.').next() == Some(last)).count() > 1;
            if clash { k.to_string() } else { last.to_string() }
        };
        let mut plans = Vec::new();
        for run in &s.runs {
            for point in &points {
                for scene in &s.scenes {
                    let scene_path = self.scene_path(scene);
                    for &seed in &s.seeds {
                        let config = self.resolve(registry, run, point, seed)?;
                        let mut id = run.name.clone();
                        for (k, v) in point {
                            id.push_str(&format!("__{}={}", label(k), value_label(v)));
                        }
                        let stem = scene_path
                            .file_name()
                            .map(|n| n.to_string_lossy().into_owned())
                            .unwrap_or_else(|| "scene".into());
                        id.push_str(&format!("__{stem}__s{seed}"));
                        let config_hash = config_hash(&config, &scene_path, s);
                        plans.push(RunPlan {
                            id: safe_name(&id),
                            name: run.name.clone(),
                            scene: scene_path.clone(),
                            seed,
                            grid: point.clone(),
                            config,
                            config_hash,
                        });
                    }
                }
            }
        }
        let mut ids: Vec<&str> = plans.iter().map(|p| p.id.as_str()).collect();
        ids.sort_unstable();
        if let Some(w) = ids.windows(2).find(|w| w[0] == w[1]) {
            return Err(self.invalid(format!("two runs get the same id `{}`", w[0])));
        }
        Ok(plans)
    }

    fn resolve(
        &self,
        registry: &Registry,
        run: &RunSpec,
        point: &[(String, Value)],
        seed: u64,
    ) -> Result<TrainConfig, AblateError> {
        let s = &self.spec;
        let ctx = |m: String| self.invalid(format!("run `{}`: {m}", run.name));
        let mut grid_patch = Value::Object(Default::default());
        for (k, v) in point {
            set_path(&mut grid_patch, k, v.clone());
        }
        // The field decides the preset: the last of base, run, grid that names one.
        let mut patch = Value::Object(Default::default());
        merge_json(&mut patch, &s.base);
        merge_json(&mut patch, &run.config);
        merge_json(&mut patch, &grid_patch);
        let field = match patch.get("field") {
            None | Some(Value::Null) => TrainConfig::default().field,
            Some(Value::String(f)) => f.clone(),
            Some(other) => return Err(ctx(format!("`field` must be a string, got {other}"))),
        };
        let entry = registry.get(&field).map_err(|e| ctx(e.to_string()))?;
        let mut v = serde_json::to_value(TrainConfig::default()).expect("TrainConfig serialises");
        // `ndc` is serialised only when off; it still exists for grid keys.
        if let Value::Object(m) = &mut v {
            m.entry("ndc").or_insert(Value::Bool(true));
        }
        merge_json(&mut v, &(entry.train_preset)());
        merge_json(&mut v, &s.base);
        merge_json(&mut v, &run.config);
        // Every grid key must name something that exists before the sweep sets it; keys under
        // `field_config` are checked against the field's defaults merged with the patch.
        for (k, _) in point {
            let exists = match k.split_once('.') {
                Some(("field_config", rest)) => {
                    let mut fc = (entry.default_config)();
                    merge_json(&mut fc, v.get("field_config").unwrap_or(&Value::Null));
                    has_path(&fc, rest)
                }
                _ => has_path(&v, k),
            };
            if !exists {
                return Err(self.invalid(format!(
                    "grid key `{k}` does not exist in the training config of run `{}` (field `{field}`)",
                    run.name
                )));
            }
        }
        merge_json(&mut v, &grid_patch);
        let mut c: TrainConfig =
            serde_json::from_value(v).map_err(|e| ctx(format!("invalid training config: {e}")))?;
        c.field = field;
        c.iters = s.budget.iters.unwrap_or(u64::MAX);
        c.time_budget_secs = s.budget.seconds;
        c.seed = seed;
        c.downscale = s.downscale;
        c.test_views = s.test_views.clone();
        c.validate().map_err(ctx)?;
        Ok(c)
    }
}

/// Sets `root[a][b]… = value` for the dotted path `a.b.…`, creating objects on the way.
fn set_path(root: &mut Value, path: &str, value: Value) {
    let mut cur = root;
    let parts: Vec<&str> = path.split('.').collect();
    for (i, p) in parts.iter().enumerate() {
        if !cur.is_object() {
            *cur = Value::Object(Default::default());
        }
        let obj = cur.as_object_mut().expect("object");
        if i + 1 == parts.len() {
            obj.insert(p.to_string(), value);
            return;
        }
        cur = obj.entry(p.to_string()).or_insert(Value::Object(Default::default()));
    }
}

/// Whether the dotted path exists in `v` (a key present with a `null` value counts).
fn has_path(v: &Value, path: &str) -> bool {
    let mut cur = v;
    for p in path.split('.') {
        match cur.as_object().and_then(|o| o.get(p)) {
            Some(x) => cur = x,
            None => return false,
        }
    }
    true
}

/// A grid value as it appears in ids and tables: strings unquoted, everything else as JSON.
pub fn value_label(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// Replaces every character outside `[A-Za-z0-9._=-]` by `-`.
pub fn safe_name(s: &str) -> String {
    s.chars()
        .map(|c| if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '=' | '-') { c } else { '-' })
        .collect()
}

/// JSON with object keys sorted at every level (independent of serde_json's map ordering).
pub fn canonical_json(v: &Value) -> String {
    match v {
        Value::Object(o) => {
            let mut keys: Vec<&String> = o.keys().collect();
            keys.sort();
            let parts: Vec<String> = keys
                .into_iter()
                .map(|k| format!("{}:{}", Value::String(k.clone()), canonical_json(&o[k])))
                .collect();
            format!("{{{}}}", parts.join(","))
        }
        Value::Array(a) => format!("[{}]", a.iter().map(canonical_json).collect::<Vec<_>>().join(",")),
        other => other.to_string(),
    }
}

/// 64-bit FNV-1a.
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

/// The hash that decides whether a finished run can be reused: FNV-1a over the canonical JSON of
/// the resolved config, the scene path, the training views and the evaluation schedule.
pub fn config_hash(config: &TrainConfig, scene: &Path, spec: &AblationSpec) -> String {
    let v = serde_json::json!({
        "config": config,
        "scene": scene.to_string_lossy(),
        "train_views": spec.train_views,
        "eval": spec.eval,
    });
    format!("{:016x}", fnv1a64(canonical_json(&v).as_bytes()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nerf_data::{Background, ViewSelection};
    use nerf_field::{FieldError, RegistryEntry};
    use serde_json::json;

    fn registry() -> Registry {
        let mut r = Registry::new();
        let fail: nerf_field::FieldBuilder =
            |_, _| Err(FieldError::InvalidConfig { field: "x".into(), message: "not built in tests".into() });
        r.register(RegistryEntry {
            name: "freq",
            description: "",
            default_config: || json!({"width": 64}),
            train_preset: || Value::Null,
            build: fail,
        });
        r.register(RegistryEntry {
            name: "grid",
            description: "",
            default_config: || json!({"grid": {"n_levels": 16, "log2_hashmap_size": 19}}),
            train_preset: || json!({"batch_rays": 7, "log_every": 3, "render_chunk_rays": 11}),
            build: fail,
        });
        r
    }

    fn parse(text: &str) -> Result<Ablation, AblateError> {
        Ablation::parse(Path::new("/abl/dir/test.toml"), text)
    }

    const MIN: &str = "scenes = [\"scene_a\"]\n[budget]\niters = 10\n[[runs]]\nname = \"r\"\n";

    #[test]
    fn defaults_are_filled_in() {
        let a = parse(MIN).unwrap();
        let s = &a.spec;
        assert_eq!(s.downscale, 1);
        assert_eq!(s.seeds, vec![0]);
        assert_eq!(s.train_views, ViewSelection::All);
        assert_eq!(s.test_views, TrainConfig::default().test_views);
        assert_eq!(s.eval, EvalSchedule::default());
        assert!(s.base.is_null() && s.grid.is_empty());
        assert_eq!(a.name(), "test");
        assert_eq!(a.default_out_dir(), Path::new("runs/ablate/test"));
        assert_eq!(a.scene_path(&s.scenes[0]), Path::new("/abl/dir/scene_a"));
        assert_eq!(a.scene_path(Path::new("/abs/x")), Path::new("/abs/x"));
        assert_eq!(a.grid_points(), vec![vec![]]);
    }

    #[test]
    fn unknown_keys_are_rejected_by_name() {
        for (text, key) in [
            (format!("sedes = [1]\n{MIN}"), "sedes"),
            (MIN.replace("iters = 10", "iters = 10\niterz = 3"), "iterz"),
            (format!("{MIN}confg = {{}}\n"), "confg"),
            (format!("{MIN}[eval]\nevery_iter = 2\n"), "every_iter"),
        ] {
            let e = parse(&text).unwrap_err();
            let msg = e.to_string();
            assert!(matches!(e, AblateError::Parse { .. }), "{msg}");
            assert!(msg.contains(key) && msg.contains("test.toml"), "{msg}");
        }
        let e = parse("scenes = [").unwrap_err();
        assert!(matches!(e, AblateError::Parse { .. }), "{e}");
    }

    #[test]
    fn missing_budget_and_runs_are_errors() {
        let e = parse("scenes = [\"s\"]\n[[runs]]\nname = \"r\"\n").unwrap_err();
        assert!(e.to_string().contains("budget"), "{e}");
        let e = parse("scenes = [\"s\"]\n[budget]\n[[runs]]\nname = \"r\"\n").unwrap_err();
        assert!(e.to_string().contains("iters") && e.to_string().contains("seconds"), "{e}");
        let e = parse("scenes = [\"s\"]\n[budget]\niters = 3\n").unwrap_err();
        assert!(e.to_string().contains("no runs"), "{e}");
        let e = parse(&format!("{MIN}[[runs]]\nname = \"r\"\n")).unwrap_err();
        assert!(e.to_string().contains("two runs"), "{e}");
        let e = parse(&format!("{MIN}[grid]\nbatch_rays = []\n")).unwrap_err();
        assert!(e.to_string().contains("batch_rays"), "{e}");
        let e = Ablation::load(Path::new("/nonexistent/abl.toml")).unwrap_err();
        assert!(matches!(e, AblateError::Read { .. }) && e.to_string().contains("/nonexistent/abl.toml"), "{e}");
    }

    #[test]
    fn grid_keys_must_exist_in_the_resolved_config() {
        let a = parse(&format!("{MIN}[grid]\nbatch_rayz = [1, 2]\n")).unwrap();
        let e = a.plan(&registry()).unwrap_err();
        assert!(e.to_string().contains("batch_rayz"), "{e}");
        // field_config paths are checked against the field's defaults.
        let text = MIN.replace("name = \"r\"", "name = \"r\"\nconfig = { field = \"grid\" }");
        let ok = parse(&format!("{text}[grid]\n\"field_config.grid.n_levels\" = [4]\n")).unwrap();
        assert_eq!(ok.plan(&registry()).unwrap()[0].config.field_config, json!({"grid": {"n_levels": 4}}));
        let bad = parse(&format!("{text}[grid]\n\"field_config.grid.n_levelz\" = [4]\n")).unwrap();
        assert!(bad.plan(&registry()).unwrap_err().to_string().contains("n_levelz"));
        // A key that exists with a null value (an unset option) is accepted.
        let opt = parse(&format!("{MIN}[grid]\ntarget_samples_per_step = [1024]\n")).unwrap();
        assert_eq!(opt.plan(&registry()).unwrap()[0].config.target_samples_per_step, Some(1024));
        // An unknown field is reported with the run name.
        let f = parse(&MIN.replace("name = \"r\"", "name = \"r\"\nconfig = { field = \"nope\" }"))
            .unwrap()
            .plan(&registry())
            .unwrap_err();
        assert!(f.to_string().contains("nope") && f.to_string().contains("`r`"), "{f}");
    }

    #[test]
    fn grid_expansion_order_and_ids() {
        let text = r#"
            scenes = ["sc/one", "/data/two"]
            seeds = [0, 5]
            [budget]
            seconds = 2.5
            [[runs]]
            name = "a run"
            [[runs]]
            name = "b"
            [grid]
            train_background = ["white", "black"]
            batch_rays = [32, 64, 128]
        "#;
        let a = parse(text).unwrap();
        let pts = a.grid_points();
        assert_eq!(pts.len(), 6);
        // sorted keys: batch_rays first (slow), train_background last (fast)
        assert_eq!(pts[0], vec![("batch_rays".into(), json!(32)), ("train_background".into(), json!("white"))]);
        assert_eq!(pts[1], vec![("batch_rays".into(), json!(32)), ("train_background".into(), json!("black"))]);
        assert_eq!(pts[2][0].1, json!(64));
        let plans = a.plan(&registry()).unwrap();
        assert_eq!(plans.len(), 2 * 6 * 2 * 2);
        assert_eq!(plans[0].id, "a-run__batch_rays=32__train_background=white__one__s0");
        assert_eq!(plans[1].id, "a-run__batch_rays=32__train_background=white__one__s5");
        assert_eq!(plans[2].id, "a-run__batch_rays=32__train_background=white__two__s0");
        assert_eq!(plans[4].id, "a-run__batch_rays=32__train_background=black__one__s0");
        assert_eq!(plans[24].id, "b__batch_rays=32__train_background=white__one__s0");
        assert_eq!(plans[2].scene, Path::new("/data/two"));
        assert_eq!(plans[1].seed, 5);
        assert_eq!(plans[4].config.train_background, Background::Black);
        assert_eq!(plans[8].config.batch_rays, 64);
        let mut ids: Vec<_> = plans.iter().map(|p| p.id.clone()).collect();
        ids.dedup();
        assert_eq!(ids.len(), plans.len());
        // Keys sharing a last segment keep their full path in the id.
        let b = parse(&format!("{MIN}[grid]\n\"lr.lr0\" = [0.1]\n\"adam.lr0\" = [1]\n")).unwrap();
        assert_eq!(b.grid_points()[0].len(), 2);
        assert_eq!(safe_name("x/y z:1"), "x-y-z-1");
    }

    #[test]
    fn config_resolution_order() {
        let text = r#"
            scenes = ["s"]
            downscale = 2
            test_views = "first:2"
            seeds = [9]
            [budget]
            iters = 40
            seconds = 3.0
            [base]
            log_every = 5
            batch_rays = 9
            [[runs]]
            name = "preset"
            config = { field = "grid" }
            [[runs]]
            name = "override"
            config = { field = "grid", batch_rays = 13, render_chunk_rays = 99 }
            [[runs]]
            name = "plain"
            config = { field = "freq", sampler = { kind = "stratified", n_samples = 4 } }
            [grid]
            render_chunk_rays = [21]
        "#;
        let plans = parse(text).unwrap().plan(&registry()).unwrap();
        let c = |i: usize| &plans[i].config;
        // preset < base: base's batch_rays and log_every win over the preset's
        assert_eq!((c(0).field.as_str(), c(0).batch_rays, c(0).log_every), ("grid", 9, 5));
        // base < run < grid
        assert_eq!((c(1).batch_rays, c(1).render_chunk_rays), (13, 21));
        // no preset for `plain`: trainer defaults elsewhere
        assert_eq!(c(2).field, "freq");
        assert_eq!(c(2).sampler, nerf_train::SamplerConfig::Stratified { n_samples: 4 });
        assert_eq!(c(2).transmittance_threshold, TrainConfig::default().transmittance_threshold);
        for p in &plans {
            assert_eq!(p.config.iters, 40);
            assert_eq!(p.config.time_budget_secs, Some(3.0));
            assert_eq!(p.config.seed, 9);
            assert_eq!(p.config.downscale, 2);
            assert_eq!(p.config.test_views, ViewSelection::First(2));
        }
        // Only a time budget: unbounded iterations.
        let t = parse(&MIN.replace("iters = 10", "seconds = 1.5")).unwrap().plan(&registry()).unwrap();
        assert_eq!((t[0].config.iters, t[0].config.time_budget_secs), (u64::MAX, Some(1.5)));
        // Invalid resolved values are reported.
        let e = parse(&format!("{MIN}[base]\nbatch_rays = 0\n")).unwrap().plan(&registry()).unwrap_err();
        assert!(e.to_string().contains("batch_rays"), "{e}");
    }

    #[test]
    fn config_hash_is_stable_and_sensitive() {
        assert_eq!(fnv1a64(b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a64(b"a"), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(canonical_json(&json!({"b": 1, "a": {"d": [1, {"z": 0, "y": 1}], "c": null}})),
            r#"{"a":{"c":null,"d":[1,{"y":1,"z":0}]},"b":1}"#);
        let text = format!("{MIN}[grid]\nbatch_rays = [32, 64]\n");
        let h = |t: &str| parse(t).unwrap().plan(&registry()).unwrap().iter().map(|p| p.config_hash.clone()).collect::<Vec<_>>();
        let base = h(&text);
        assert_eq!(base, h(&text), "same file, same hashes");
        assert!(base.iter().all(|x| x.len() == 16 && x.chars().all(|c| c.is_ascii_hexdigit())));
        assert_ne!(base[0], base[1], "grid value changes the hash");
        // Fixed value: the hash must not depend on process state (RandomState) or map order.
        let plan = &parse(&text).unwrap().plan(&registry()).unwrap()[0];
        let again = config_hash(&plan.config, &plan.scene, &parse(&text).unwrap().spec);
        assert_eq!(again, plan.config_hash);
        for changed in [
            text.replace("iters = 10", "iters = 11"),
            text.replace("iters = 10", "iters = 10\nseconds = 5.0"),
            text.replace("scene_a", "scene_b"),
            format!("seeds = [1]\n{text}"),
            format!("train_views = \"first:2\"\n{text}"),
            format!("{text}[eval]\nevery_iters = 5\n"),
            format!("{text}[base]\nlog_every = 7\n"),
        ] {
            assert_ne!(h(&changed)[0], base[0], "{changed}");
        }
        // The run name is not part of the config: renaming keeps the hash.
        assert_eq!(h(&text.replace("name = \"r\"", "name = \"q\""))[0], base[0]);
    }

    #[test]
    fn the_ray_space_is_a_grid_key_and_its_default_keeps_old_hashes() {
        let plans = parse(&format!("{MIN}[grid]\nndc = [true, false]\n")).unwrap().plan(&registry()).unwrap();
        assert_eq!(plans.iter().map(|p| p.config.ndc).collect::<Vec<_>>(), [true, false]);
        assert!(plans[0].id.contains("ndc=true") && plans[1].id.contains("ndc=false"), "{}", plans[1].id);
        // `ndc = true` is the default and is not serialised: the same hash as a file without it.
        let plain = parse(MIN).unwrap().plan(&registry()).unwrap();
        assert_eq!(plans[0].config_hash, plain[0].config_hash);
        assert_ne!(plans[1].config_hash, plain[0].config_hash);
    }
}
