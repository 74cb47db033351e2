//! Checkpoints: a JSON header followed by raw little-endian `f32` tensors, written atomically
//! (temporary file, fsync, rename) so a crash or Ctrl-C never leaves a torn checkpoint.
//!
//! Layout: `b"NERFCKPT"`, `u64` header length (LE), header JSON, then every tensor's values in
//! header order, then (header `"crc32": true`) the CRC-32 of every byte before it as a `u32` (LE),
//! so that a corrupted file is refused by name instead of loading wrong weights. Checkpoints
//! written before the checksum (no `crc32` key) load without the check.

use crate::config::TrainConfig;
use crate::TrainError;
use nerf_optim::AdamState;
use serde::{Deserialize, Serialize};
use std::io::{Read, Write};
use std::path::Path;

const MAGIC: &[u8; 8] = b"NERFCKPT";
const VERSION: u32 = 1;

/// Everything needed to resume a run.
#[derive(Clone, Debug)]
pub struct Checkpoint {
    /// Steps taken.
    pub step: u64,
    /// Training seconds spent so far (excluding evaluation).
    pub elapsed_secs: f64,
    /// Field samples processed so far.
    pub samples_seen: u64,
    /// The run's config.
    pub config: TrainConfig,
    /// Parameters per field instance, by group name.
    pub fields: Vec<Vec<(String, Vec<f32>)>>,
    /// Optimiser state.
    pub adam: AdamState,
    /// Sampler state (occupancy grid, batch sizing) by name, and — for runs with `ema_decay` — the
    /// parameters' moving average (`ema/step`, `ema/<group>`: see
    /// [`Trainer::sampler_state`](crate::Trainer::sampler_state)). Checkpoints of runs without an
    /// average simply lack those entries.
    pub sampler: Vec<(String, Vec<f32>)>,
    /// A render-only copy ([`Checkpoint::for_rendering`]): the weights renders use, no optimiser
    /// state. Rendering, evaluation and export read it; resuming training from it is refused.
    pub render_only: bool,
}

#[derive(Serialize, Deserialize)]
struct Header {
    format: String,
    version: u32,
    step: u64,
    elapsed_secs: f64,
    samples_seen: u64,
    config: TrainConfig,
    adam_step: u64,
    /// (field index, group name, length)
    fields: Vec<(usize, String, usize)>,
    /// (group name, length) — m then v for each.
    adam: Vec<(String, usize)>,
    /// (name, length) of sampler state tensors, stored last.
    #[serde(default)]
    sampler: Vec<(String, usize)>,
    /// (group name, length) of the per-entry Adam step counts of sparse groups (u32), stored
    /// after the sampler state.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    adam_steps: Vec<(String, usize)>,
    /// [`Checkpoint::render_only`]; absent (false) in a full checkpoint.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    render_only: bool,
    /// A CRC-32 of the file's preceding bytes follows the tensors; absent (false) in checkpoints
    /// written before it was added.
    #[serde(default)]
    crc32: bool,
}

/// A writer that keeps the CRC-32 of everything written through it.
struct Crc32Writer<W> {
    inner: W,
    hasher: crc32fast::Hasher,
}

impl<W: Write> Write for Crc32Writer<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hasher.update(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

fn ck_err(path: &Path, message: impl Into<String>) -> TrainError {
    TrainError::Checkpoint { path: path.to_path_buf(), message: message.into() }
}

impl Checkpoint {
    /// Writes the checkpoint atomically to `path`.
    pub fn save(&self, path: &Path) -> Result<(), TrainError> {
        let header = Header {
            format: "nerf-rs checkpoint".into(),
            version: VERSION,
            step: self.step,
            elapsed_secs: self.elapsed_secs,
            samples_seen: self.samples_seen,
            config: self.config.clone(),
            adam_step: self.adam.step,
            fields: self
                .fields
                .iter()
                .enumerate()
                .flat_map(|(i, gs)| gs.iter().map(move |(n, v)| (i, n.clone(), v.len())))
                .collect(),
            adam: self.adam.groups.iter().map(|(n, m, _)| (n.clone(), m.len())).collect(),
            sampler: self.sampler.iter().map(|(n, v)| (n.clone(), v.len())).collect(),
            adam_steps: self.adam.steps.iter().map(|(n, k)| (n.clone(), k.len())).collect(),
            render_only: self.render_only,
            crc32: true,
        };
        let json = serde_json::to_vec(&header).map_err(|e| ck_err(path, e.to_string()))?;
        let tmp = path.with_extension("tmp");
        let io = |e: std::io::Error| TrainError::Io { path: tmp.clone(), source: e };
        let file = std::fs::File::create(&tmp).map_err(io)?;
        let mut w = Crc32Writer { inner: std::io::BufWriter::new(file), hasher: crc32fast::Hasher::new() };
        w.write_all(MAGIC).map_err(io)?;
        w.write_all(&(json.len() as u64).to_le_bytes()).map_err(io)?;
        w.write_all(&json).map_err(io)?;
        let mut put = |v: &[f32]| -> std::io::Result<()> {
            for chunk in v.chunks(1 << 16) {
                let bytes: Vec<u8> = chunk.iter().flat_map(|x| x.to_le_bytes()).collect();
                w.write_all(&bytes)?;
            }
            Ok(())
        };
        for gs in &self.fields {
            for (_, v) in gs {
                put(v).map_err(io)?;
            }
        }
        for (_, m, v) in &self.adam.groups {
            put(m).map_err(io)?;
            put(v).map_err(io)?;
        }
        for (_, v) in &self.sampler {
            put(v).map_err(io)?;
        }
        for (_, k) in &self.adam.steps {
            for chunk in k.chunks(1 << 16) {
                let bytes: Vec<u8> = chunk.iter().flat_map(|x| x.to_le_bytes()).collect();
                w.write_all(&bytes).map_err(io)?;
            }
        }
        let crc = w.hasher.finalize();
        let mut w = w.inner;
        w.write_all(&crc.to_le_bytes()).map_err(io)?;
        let file = w.into_inner().map_err(|e| io(e.into_error()))?;
        file.sync_all().map_err(io)?;
        drop(file);
        std::fs::rename(&tmp, path).map_err(|e| TrainError::Io { path: path.to_path_buf(), source: e })?;
        Ok(())
    }

    /// Reads a checkpoint written by [`Checkpoint::save`].
    pub fn load(path: &Path) -> Result<Self, TrainError> {
        let mut f = std::fs::File::open(path).map_err(|e| TrainError::Io { path: path.to_path_buf(), source: e })?;
        let mut bytes = Vec::new();
        f.read_to_end(&mut bytes).map_err(|e| TrainError::Io { path: path.to_path_buf(), source: e })?;
        let (h, hlen) = parse_header(path, &bytes)?;
        // The file's size must be what the header's tensor lengths say (checked before any of them
        // sizes an allocation), then the checksum must match.
        let words = h
            .fields
            .iter()
            .map(|(_, _, n)| Some(*n))
            .chain(h.adam.iter().map(|(_, n)| n.checked_mul(2)))
            .chain(h.sampler.iter().chain(&h.adam_steps).map(|(_, n)| Some(*n)))
            .try_fold(0usize, |acc, n| acc.checked_add(n?));
        let expected = words
            .and_then(|w| w.checked_mul(4))
            .and_then(|b| b.checked_add(16 + hlen + if h.crc32 { 4 } else { 0 }))
            .ok_or_else(|| ck_err(path, "bad header: tensor lengths overflow"))?;
        if bytes.len() < expected {
            return Err(ck_err(path, format!("truncated tensor data ({} of {expected} bytes)", bytes.len())));
        }
        if bytes.len() > expected {
            return Err(ck_err(path, format!("trailing bytes after tensor data ({} bytes, {expected} expected)", bytes.len())));
        }
        let data = &bytes[..expected - if h.crc32 { 4 } else { 0 }];
        if h.crc32 {
            let stored = u32::from_le_bytes(bytes[data.len()..].try_into().expect("4 bytes"));
            let computed = crc32fast::hash(data);
            if stored != computed {
                return Err(ck_err(
                    path,
                    format!("checksum mismatch (stored CRC-32 {stored:08x}, computed {computed:08x}): the file is corrupted"),
                ));
            }
        }
        let mut pos = 16 + hlen;
        // The lengths sum to the data's size (checked above): every slice below is in bounds.
        let mut take = |len: usize| -> Vec<f32> {
            let raw = &data[pos..pos + 4 * len];
            pos += 4 * len;
            raw.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
        };
        let n_fields = h.fields.iter().map(|(i, _, _)| i.saturating_add(1)).max().unwrap_or(0);
        if n_fields > h.fields.len() {
            return Err(ck_err(path, format!("bad header: field instance {} of {} tensor groups", n_fields - 1, h.fields.len())));
        }
        let mut fields = vec![Vec::new(); n_fields];
        for (i, name, len) in &h.fields {
            fields[*i].push((name.clone(), take(*len)));
        }
        let mut groups = Vec::new();
        for (name, len) in &h.adam {
            let m = take(*len);
            let v = take(*len);
            groups.push((name.clone(), m, v));
        }
        let mut sampler = Vec::new();
        for (name, len) in &h.sampler {
            sampler.push((name.clone(), take(*len)));
        }
        let mut steps = Vec::new();
        for (name, len) in &h.adam_steps {
            // The same 4-byte little-endian words, read as u32.
            steps.push((name.clone(), take(*len).into_iter().map(f32::to_bits).collect()));
        }
        debug_assert_eq!(pos, data.len(), "the header's lengths were checked against the file's size");
        Ok(Self {
            step: h.step,
            elapsed_secs: h.elapsed_secs,
            samples_seen: h.samples_seen,
            config: h.config,
            fields,
            adam: AdamState { step: h.adam_step, groups, steps },
            sampler,
            render_only: h.render_only,
        })
    }
}

impl Checkpoint {
    /// A render-only copy: what rendering reads and nothing that only training needs, about a
    /// quarter of a run's checkpoint with Adam and a moving average (`nerf slim`: small enough to
    /// bring a lent GPU's field home and score it elsewhere). The parameters are the ones renders
    /// use: the moving average for a run with `ema_decay` (once it has one), which then replaces
    /// them, with `ema_decay` cleared so that nothing averages again. No optimiser state is kept;
    /// the occupancy grid, batch sizing and any colour or pose corrections are. Rendering this
    /// copy gives what rendering the full checkpoint gives. Errors when the moving average lacks
    /// a group of the parameters or has another length.
    pub fn for_rendering(&self) -> Result<Checkpoint, TrainError> {
        let (ema, rest) = crate::trainer::ema_from_entries(&self.sampler)?;
        let mut fields = self.fields.clone();
        let mut config = self.config.clone();
        if let Some(e) = ema.filter(|e| e.step > 0 && self.config.ema_decay.is_some()) {
            let prefixes = crate::trainer::group_prefixes(fields.len());
            let names: Vec<Vec<String>> = fields
                .iter()
                .zip(prefixes)
                .map(|(groups, prefix)| groups.iter().map(|(name, _)| format!("{prefix}/{name}")).collect())
                .collect();
            crate::trainer::check_ema_groups(&e, &names, &fields)?;
            for (groups, names) in fields.iter_mut().zip(&names) {
                for ((_, values), key) in groups.iter_mut().zip(names) {
                    let (_, avg) = e.groups.iter().find(|(n, _)| n == key).expect("checked above");
                    values.clone_from(avg);
                }
            }
        }
        config.ema_decay = None;
        Ok(Checkpoint {
            step: self.step,
            elapsed_secs: self.elapsed_secs,
            samples_seen: self.samples_seen,
            config,
            fields,
            adam: AdamState { step: 0, groups: Vec::new(), steps: Vec::new() },
            sampler: rest,
            render_only: true,
        })
    }

    /// The step a checkpoint was written at, reading only its header (not the tensors).
    pub fn read_step(path: &Path) -> Result<u64, TrainError> {
        let io = |e| TrainError::Io { path: path.to_path_buf(), source: e };
        let mut f = std::fs::File::open(path).map_err(io)?;
        let mut prefix = [0u8; 16];
        let got = read_up_to(&mut f, &mut prefix).map_err(io)?;
        // A short or foreign file: let the parser name the problem.
        let hlen = if got == 16 && &prefix[..8] == MAGIC {
            u64::from_le_bytes(prefix[8..16].try_into().unwrap()) as usize
        } else {
            0
        };
        let mut bytes = prefix[..got].to_vec();
        f.take(hlen as u64).read_to_end(&mut bytes).map_err(io)?;
        Ok(parse_header(path, &bytes)?.0.step)
    }
}

/// Reads until `buf` is full or the file ends; the bytes read.
fn read_up_to(f: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match f.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}

/// The header of a checkpoint whose bytes start `bytes` (at least the magic, the length and the
/// header), and the header's length.
fn parse_header(path: &Path, bytes: &[u8]) -> Result<(Header, usize), TrainError> {
    if bytes.len() < 16 || &bytes[..8] != MAGIC {
        return Err(ck_err(path, "not a nerf-rs checkpoint (bad magic)"));
    }
    let hlen = u64::from_le_bytes(bytes[8..16].try_into().unwrap()) as usize;
    let body = bytes.get(16..16usize.saturating_add(hlen)).ok_or_else(|| ck_err(path, "truncated header"))?;
    let h: Header = serde_json::from_slice(body).map_err(|e| ck_err(path, format!("bad header: {e}")))?;
    if h.version != VERSION {
        return Err(ck_err(path, format!("unsupported checkpoint version {}", h.version)));
    }
    Ok((h, hlen))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nerf_optim::EmaState;

    #[test]
    fn round_trip_and_corruption_is_reported() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.bin");
        let ck = Checkpoint {
            step: 42,
            elapsed_secs: 1.5,
            samples_seen: 99,
            config: TrainConfig::default(),
            fields: vec![vec![("a".into(), vec![1.0, -2.0]), ("b".into(), vec![3.5])], vec![("a".into(), vec![0.25])]],
            adam: AdamState {
                step: 7,
                groups: vec![("g".into(), vec![0.1, 0.2], vec![0.3, 0.4])],
                steps: vec![("g".into(), vec![7, 3])],
            },
            sampler: vec![("occ".into(), vec![0.5; 3])],
            render_only: false,
        };
        ck.save(&p).unwrap();
        assert!(!p.with_extension("tmp").exists(), "temporary file must be renamed away");
        let back = Checkpoint::load(&p).unwrap();
        assert_eq!(back.step, 42);
        assert_eq!(back.fields, ck.fields);
        assert_eq!(back.adam.groups, ck.adam.groups);
        assert_eq!(back.adam.steps, ck.adam.steps);
        assert_eq!(back.adam.step, 7);
        assert_eq!(back.sampler, ck.sampler);
        assert!(!back.render_only);
        // One flipped bit anywhere — header or tensors — is refused, naming the file.
        let bytes = std::fs::read(&p).unwrap();
        for at in [20, bytes.len() - 30, bytes.len() - 6, bytes.len() - 1] {
            let mut bad = bytes.clone();
            bad[at] ^= 0x10;
            std::fs::write(&p, &bad).unwrap();
            match Checkpoint::load(&p) {
                Err(e) => {
                    let e = e.to_string();
                    assert!(e.contains("c.bin") && (e.contains("checksum mismatch") || e.contains("bad header")), "byte {at}: {e}");
                }
                Ok(_) => panic!("a flipped bit at byte {at} of {} was not noticed", bytes.len()),
            }
        }
        // A checkpoint written before the checksum (no `crc32` key, no trailer) still loads.
        let hlen = u64::from_le_bytes(bytes[8..16].try_into().unwrap()) as usize;
        let mut header: serde_json::Value = serde_json::from_slice(&bytes[16..16 + hlen]).unwrap();
        assert_eq!(header["crc32"], serde_json::Value::Bool(true));
        header.as_object_mut().unwrap().remove("crc32");
        let json = serde_json::to_vec(&header).unwrap();
        let mut old = MAGIC.to_vec();
        old.extend((json.len() as u64).to_le_bytes());
        old.extend(&json);
        old.extend(&bytes[16 + hlen..bytes.len() - 4]);
        std::fs::write(&p, &old).unwrap();
        let back = Checkpoint::load(&p).unwrap();
        assert_eq!((back.fields, back.adam.groups), (ck.fields.clone(), ck.adam.groups.clone()));
        // A header whose lengths do not fit the file (here one tensor of 2^60 values) is refused
        // before it sizes anything.
        for (len, needle) in [(1u64 << 60, "truncated"), (u64::MAX / 2, "overflow")] {
            header["fields"][0][2] = serde_json::json!(len);
            let json = serde_json::to_vec(&header).unwrap();
            let mut huge = MAGIC.to_vec();
            huge.extend((json.len() as u64).to_le_bytes());
            huge.extend(&json);
            huge.extend(&bytes[16 + hlen..]);
            std::fs::write(&p, &huge).unwrap();
            let e = Checkpoint::load(&p).unwrap_err().to_string();
            assert!(e.contains("c.bin") && e.contains(needle), "{e}");
        }
        std::fs::write(&p, &bytes).unwrap();
        // Truncate: the error names the file.
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() - 3]).unwrap();
        let e = Checkpoint::load(&p).unwrap_err().to_string();
        assert!(e.contains("c.bin") && e.contains("truncated"), "{e}");
        // The header alone is intact: its step can still be read.
        assert_eq!(Checkpoint::read_step(&p).unwrap(), 42);
        std::fs::write(&p, &bytes[..40]).unwrap();
        let e = Checkpoint::read_step(&p).unwrap_err().to_string();
        assert!(e.contains("c.bin") && e.contains("truncated header"), "{e}");
        std::fs::write(&p, b"garbage").unwrap();
        assert!(Checkpoint::load(&p).unwrap_err().to_string().contains("magic"));
        assert!(Checkpoint::read_step(&p).unwrap_err().to_string().contains("magic"));
        let e = Checkpoint::read_step(&dir.path().join("none.bin")).unwrap_err().to_string();
        assert!(e.contains("none.bin"), "{e}");
    }

    /// A checkpoint of one field instance with groups `a` and `b`, Adam state, an occupancy
    /// entry and (with `ema`) a moving average of both groups.
    fn with_average(ema: bool) -> Checkpoint {
        let config = TrainConfig { ema_decay: ema.then_some(0.95), ..TrainConfig::default() };
        let mut sampler = vec![("occupancy_density".to_string(), vec![0.5, 0.0, 2.0])];
        if ema {
            let avg = EmaState { step: 5, groups: vec![("field/a".into(), vec![9.0, -9.0]), ("field/b".into(), vec![8.0])] };
            sampler.extend(crate::trainer::ema_to_entries(&avg));
        }
        Checkpoint {
            step: 5,
            elapsed_secs: 2.0,
            samples_seen: 10,
            config,
            fields: vec![vec![("a".into(), vec![1.0, -2.0]), ("b".into(), vec![3.5])]],
            adam: AdamState { step: 5, groups: vec![("field/a".into(), vec![0.1, 0.2], vec![0.3, 0.4])], steps: Vec::new() },
            sampler,
            render_only: false,
        }
    }

    #[test]
    fn a_render_only_copy_holds_the_averaged_weights_and_no_optimiser_state() {
        let slim = with_average(true).for_rendering().unwrap();
        assert_eq!(slim.fields, vec![vec![("a".to_string(), vec![9.0, -9.0]), ("b".to_string(), vec![8.0])]]);
        assert_eq!(slim.config.ema_decay, None, "nothing averages the averaged weights again");
        assert!(slim.adam.groups.is_empty() && slim.adam.steps.is_empty());
        assert_eq!(slim.sampler, vec![("occupancy_density".to_string(), vec![0.5, 0.0, 2.0])]);
        assert!(slim.render_only);
        assert_eq!((slim.step, slim.samples_seen), (5, 10));
        // The marker survives a save and a load.
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("slim.bin");
        slim.save(&p).unwrap();
        let back = Checkpoint::load(&p).unwrap();
        assert!(back.render_only);
        assert_eq!(back.fields, slim.fields);
        // Without an average the parameters are kept as they are.
        let plain = with_average(false).for_rendering().unwrap();
        assert_eq!(plain.fields, with_average(false).fields);
        // An average that does not cover the parameters is an error, not a mix.
        let mut bad = with_average(true);
        bad.sampler.retain(|(n, _)| n != "ema/field/b");
        let e = bad.for_rendering().unwrap_err().to_string();
        assert!(e.contains("field/b"), "{e}");
        let mut short = with_average(true);
        for (n, v) in &mut short.sampler {
            if n == "ema/field/a" {
                v.pop();
            }
        }
        let e = short.for_rendering().unwrap_err().to_string();
        assert!(e.contains("field/a") && e.contains("1 values"), "{e}");
    }
}
