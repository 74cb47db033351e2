//! Small shared plumbing for every kernel family: compute pipelines built once from a WGSL source,
//! recording a dispatch into a caller's command encoder (so a whole training step is one
//! submission), 1-D launches larger than 65 535 workgroups, and host↔device buffer helpers used by
//! the tests and by set-up code (never inside a training step).
//!
//! Launch convention for every kernel: a 1-D problem of `n` invocations is launched with
//! [`groups_1d`]; the WGSL computes its linear index as
//! `let i = gid.x + gid.y * nwg.x * WG;` with `@builtin(num_workgroups) nwg` and returns when
//! `i >= n`. Dynamic sizes (the number of rays or samples of a step, known only on the device) are
//! read from the `counters` buffer (slots in [`crate::layout`]); kernels are launched for the
//! capacity and the extra invocations return at once.

use crate::{GpuContext, GpuError};
use wgpu::util::DeviceExt;

/// Largest workgroup count per dimension that every adapter accepts.
pub const MAX_GROUPS_PER_DIM: u32 = 65_535;

/// Workgroup counts for `n` invocations in groups of `wg`: `[x, y, 1]` with `x ≤ 65 535`.
pub fn groups_1d(n: usize, wg: u32) -> [u32; 3] {
    let groups = (n as u64).div_ceil(wg as u64).max(1);
    if groups <= MAX_GROUPS_PER_DIM as u64 {
        [groups as u32, 1, 1]
    } else {
        let y = groups.div_ceil(MAX_GROUPS_PER_DIM as u64);
        let x = groups.div_ceil(y);
        [x as u32, y as u32, 1]
    }
}

/// One compute entry point of one WGSL source, compiled once. Bind groups are cached by the
/// buffers they bind, so a training step that binds the same buffers every time creates none.
pub struct Kernel {
    pipeline: wgpu::ComputePipeline,
    label: String,
    cache: std::sync::Mutex<BindGroupCache>,
}

/// The begin/end timestamp writes of a pass that [`GpuContext::profile_pass`] chose to time.
fn timestamp_writes(timed: &Option<(wgpu::QuerySet, u32)>) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
    timed.as_ref().map(|(query_set, i)| wgpu::ComputePassTimestampWrites {
        query_set,
        beginning_of_pass_write_index: Some(*i),
        end_of_pass_write_index: Some(i + 1),
    })
}

/// Bind groups by a hash of what they bind, with the bindings kept to rule out collisions.
type BindGroupCache = std::collections::HashMap<u64, (Vec<(u32, wgpu::Buffer, u64)>, wgpu::BindGroup)>;

/// A storage binding: a buffer from byte `offset` to its end. A whole buffer converts to one at
/// offset 0, so every `(binding, &buffer)` list binds as before; a binding at an offset lets a
/// kernel read and write rows `first_row..` of a larger buffer in place (a chunk of the marched
/// samples, `nerf_field::ChunkedDensity`). The offset must be a multiple of the device's
/// `min_storage_buffer_offset_alignment` ([`GpuContext::storage_offset_alignment`]).
#[derive(Clone, Copy, Debug)]
pub struct Bound<'a> {
    /// The buffer.
    pub buffer: &'a wgpu::Buffer,
    /// Bytes skipped at its start.
    pub offset: u64,
}

impl<'a> Bound<'a> {
    /// Rows `first_row..` of `buffer`, rows of `row_floats` f32.
    pub fn rows(buffer: &'a wgpu::Buffer, row_floats: usize, first_row: usize) -> Self {
        Bound { buffer, offset: 4 * (row_floats * first_row) as u64 }
    }

    /// Bytes from the offset to the buffer's end (what a kernel sees as its array's size).
    pub fn size(&self) -> u64 {
        self.buffer.size().saturating_sub(self.offset)
    }
}

impl<'a> From<&'a wgpu::Buffer> for Bound<'a> {
    fn from(buffer: &'a wgpu::Buffer) -> Self {
        Bound { buffer, offset: 0 }
    }
}

/// Cached bind groups per kernel before the cache is emptied (tests that bind fresh buffers on
/// every call would otherwise keep them alive).
const BIND_GROUP_CACHE: usize = 64;

impl Kernel {
    /// Compiles `entry` of `source` with pipeline-overridable constants.
    pub fn new(ctx: &GpuContext, source: &str, entry: &str, constants: &[(&str, f64)]) -> Self {
        let module = ctx.shader_module(entry, source);
        Self::from_module(ctx, &module, entry, constants)
    }

    /// As [`Kernel::new`] for a module already created (several entry points of one file).
    pub fn from_module(ctx: &GpuContext, module: &wgpu::ShaderModule, entry: &str, constants: &[(&str, f64)]) -> Self {
        let pipeline = ctx.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(entry),
            layout: None,
            module,
            entry_point: Some(entry),
            compilation_options: wgpu::PipelineCompilationOptions {
                constants,
                zero_initialize_workgroup_memory: false,
            },
            cache: None,
        });
        Self { pipeline, label: entry.to_string(), cache: Default::default() }
    }

    /// Bind groups currently cached (one per distinct set of bound buffers).
    pub fn cached_bind_groups(&self) -> usize {
        self.cache.lock().unwrap_or_else(|e| e.into_inner()).len()
    }

    /// The entry point's name.
    pub fn label(&self) -> &str {
        &self.label
    }

    /// Records one dispatch into `enc`; `bindings` are `(binding index, buffer)` of group 0 (whole
    /// buffers, or [`Bound`] from an offset). Bindings the shader does not use must not be passed
    /// (auto layout).
    pub fn record<'b, B: Into<Bound<'b>> + Copy>(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, bindings: &[(u32, B)], groups: [u32; 3]) {
        let group = self.bind_group(ctx, bindings);
        let timed = ctx.profile_pass(&self.label);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some(&self.label), timestamp_writes: timestamp_writes(&timed) });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &group, &[]);
        pass.dispatch_workgroups(groups[0], groups[1], groups[2]);
    }

    /// Records one dispatch whose workgroup counts are read on the device from `indirect` at
    /// byte `offset` (three `u32`, written by an earlier kernel).
    pub fn record_indirect<'b, B: Into<Bound<'b>> + Copy>(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        bindings: &[(u32, B)],
        indirect: &wgpu::Buffer,
        offset: u64,
    ) {
        let group = self.bind_group(ctx, bindings);
        let timed = ctx.profile_pass(&self.label);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some(&self.label), timestamp_writes: timestamp_writes(&timed) });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &group, &[]);
        pass.dispatch_workgroups_indirect(indirect, offset);
    }

    fn bind_group<'b, B: Into<Bound<'b>> + Copy>(&self, ctx: &GpuContext, bindings: &[(u32, B)]) -> wgpu::BindGroup {
        use std::hash::{Hash, Hasher};
        let bindings: Vec<(u32, Bound<'b>)> = bindings.iter().map(|&(i, b)| (i, b.into())).collect();
        let mut h = std::collections::hash_map::DefaultHasher::new();
        for (i, b) in &bindings {
            i.hash(&mut h);
            b.buffer.hash(&mut h);
            b.offset.hash(&mut h);
        }
        let key = h.finish();
        let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((bound, group)) = cache.get(&key) {
            if bound.len() == bindings.len()
                && bound.iter().zip(&bindings).all(|((i, b, o), (j, c))| i == j && b == c.buffer && *o == c.offset)
            {
                return group.clone();
            }
        }
        let group = self.create_bind_group(ctx, &bindings);
        if cache.len() >= BIND_GROUP_CACHE {
            cache.clear();
        }
        cache.insert(key, (bindings.iter().map(|(i, b)| (*i, b.buffer.clone(), b.offset)).collect(), group.clone()));
        group
    }

    fn create_bind_group(&self, ctx: &GpuContext, bindings: &[(u32, Bound<'_>)]) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = bindings
            .iter()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: *i,
                resource: match b.offset {
                    0 => b.buffer.as_entire_binding(),
                    offset => wgpu::BindingResource::Buffer(wgpu::BufferBinding { buffer: b.buffer, offset, size: None }),
                },
            })
            .collect();
        ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(&self.label),
            layout: &self.pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    /// Records and submits one dispatch on its own (tests and set-up).
    pub fn run<'b, B: Into<Bound<'b>> + Copy>(&self, ctx: &GpuContext, bindings: &[(u32, B)], groups: [u32; 3]) {
        let mut enc = ctx.encoder(&self.label);
        self.record(ctx, &mut enc, bindings, groups);
        ctx.queue.submit([enc.finish()]);
    }
}

/// Usage of every storage buffer made by the helpers: bindable, writable from the host, copyable
/// both ways, usable as indirect-dispatch arguments.
pub const STORAGE_USAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC)
    .union(wgpu::BufferUsages::INDIRECT);

impl GpuContext {
    /// A new command encoder.
    pub fn encoder(&self, label: &str) -> wgpu::CommandEncoder {
        self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
    }

    /// A storage buffer of `bytes` bytes (at least 4), zero-initialised.
    pub fn zeros(&self, label: &str, bytes: usize) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: (bytes.max(4) as u64).next_multiple_of(4),
            usage: STORAGE_USAGE,
            mapped_at_creation: false,
        })
    }

    /// Largest storage buffer one binding can cover on this device (the smaller of the buffer size
    /// and storage-binding limits).
    pub fn max_storage_bytes(&self) -> u64 {
        let l = self.device.limits();
        l.max_buffer_size.min(l.max_storage_buffer_binding_size)
    }

    /// As [`GpuContext::zeros`] for buffers whose size follows the samples per launch: a
    /// [`GpuError::CapacityTooLarge`] that names the buffer, its size and the device's limit when
    /// `bytes` exceeds [`GpuContext::max_storage_bytes`] (wgpu would panic on it).
    pub fn zeros_checked(&self, label: &str, bytes: usize) -> Result<wgpu::Buffer, GpuError> {
        let limit = self.max_storage_bytes();
        if bytes as u64 > limit {
            return Err(GpuError::CapacityTooLarge {
                label: label.to_string(),
                bytes: bytes as u64,
                limit,
                adapter: self.info.name.clone(),
            });
        }
        Ok(self.zeros(label, bytes))
    }

    /// The buffers of `capacity` samples each of a field or stage, `(label, floats per sample)`,
    /// as [`GpuContext::zeros_checked`]; all sizes are checked before any is made, so an error
    /// names the largest buffer, whose overshoot says how many samples fit.
    pub fn zeros_per_sample<const N: usize>(
        &self,
        capacity: usize,
        buffers: [(&str, usize); N],
    ) -> Result<[wgpu::Buffer; N], GpuError> {
        let bytes = |floats: usize| 4usize.saturating_mul(floats).saturating_mul(capacity);
        if let Some(&(label, floats)) = buffers.iter().max_by_key(|(_, floats)| *floats) {
            let limit = self.max_storage_bytes();
            if bytes(floats) as u64 > limit {
                return Err(GpuError::CapacityTooLarge {
                    label: label.to_string(),
                    bytes: bytes(floats) as u64,
                    limit,
                    adapter: self.info.name.clone(),
                });
            }
        }
        Ok(buffers.map(|(label, floats)| self.zeros(label, bytes(floats))))
    }

    /// A storage buffer holding `data` (an empty slice gives a 4-byte buffer: bindings must not be empty).
    #[allow(clippy::manual_is_multiple_of)] // keeps the MSRV (1.85)
    pub fn upload<T: bytemuck::Pod>(&self, label: &str, data: &[T]) -> wgpu::Buffer {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let pad;
        let bytes = if bytes.len() % 4 != 0 || bytes.is_empty() {
            pad = {
                let mut v = bytes.to_vec();
                v.resize(bytes.len().max(4).next_multiple_of(4), 0);
                v
            };
            &pad[..]
        } else {
            bytes
        };
        self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some(label), contents: bytes, usage: STORAGE_USAGE })
    }

    /// A uniform buffer holding `value` (rewritable with [`GpuContext::write`]).
    pub fn uniform<T: bytemuck::Pod>(&self, label: &str, value: &T) -> wgpu::Buffer {
        self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytemuck::bytes_of(value),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        })
    }

    /// Queues a host→device write (lands before the next submission; no round trip).
    pub fn write<T: bytemuck::Pod>(&self, buffer: &wgpu::Buffer, offset: u64, data: &[T]) {
        self.queue.write_buffer(buffer, offset, bytemuck::cast_slice(data));
    }

    /// Reads `len` values of type `T` from the start of `src` (waits for the queue).
    pub fn read<T: bytemuck::Pod>(&self, src: &wgpu::Buffer, len: usize) -> Result<Vec<T>, GpuError> {
        let size = ((std::mem::size_of::<T>() * len).max(4) as u64).next_multiple_of(4);
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("staging"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self.encoder("read");
        enc.copy_buffer_to_buffer(src, 0, &staging, 0, size);
        let idx = self.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::Wait { submission_index: Some(idx), timeout: None })
            .map_err(|e| GpuError::ReadBack(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::ReadBack(e.to_string()))?
            .map_err(|e| GpuError::ReadBack(e.to_string()))?;
        let view = staging.get_mapped_range(..).map_err(|e| GpuError::ReadBack(format!("{e:?}")))?;
        let bytes = &view[..std::mem::size_of::<T>() * len];
        let out: Vec<T> = bytemuck::pod_collect_to_vec(bytes);
        drop(view);
        staging.unmap();
        Ok(out)
    }

    /// Reads the first `len` 32-bit words of several buffers with one copy and one wait (rendering
    /// reads colour, opacity, depth and the counters of a chunk this way).
    pub fn read_words(&self, parts: &[(&wgpu::Buffer, usize)]) -> Result<Vec<Vec<u32>>, GpuError> {
        let total: usize = parts.iter().map(|(_, n)| n).sum();
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("staging"),
            size: (4 * total.max(1)) as u64,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self.encoder("read");
        let mut offset = 0u64;
        for (buf, n) in parts {
            if *n > 0 {
                enc.copy_buffer_to_buffer(buf, 0, &staging, offset, (4 * n) as u64);
            }
            offset += (4 * n) as u64;
        }
        let idx = self.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::Wait { submission_index: Some(idx), timeout: None })
            .map_err(|e| GpuError::ReadBack(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::ReadBack(e.to_string()))?
            .map_err(|e| GpuError::ReadBack(e.to_string()))?;
        let view = staging.get_mapped_range(..).map_err(|e| GpuError::ReadBack(format!("{e:?}")))?;
        let words: &[u32] = bytemuck::cast_slice(&view[..4 * total]);
        let mut out = Vec::with_capacity(parts.len());
        let mut at = 0;
        for (_, n) in parts {
            out.push(words[at..at + n].to_vec());
            at += n;
        }
        drop(view);
        staging.unmap();
        Ok(out)
    }

    /// Reads `len` f32 values.
    pub fn read_f32(&self, src: &wgpu::Buffer, len: usize) -> Result<Vec<f32>, GpuError> {
        self.read::<f32>(src, len)
    }

    /// Reads `len` u32 values.
    pub fn read_u32(&self, src: &wgpu::Buffer, len: usize) -> Result<Vec<u32>, GpuError> {
        self.read::<u32>(src, len)
    }

    /// Waits until everything submitted so far has finished.
    pub fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::Wait { submission_index: None, timeout: None })
            .map(|_| ())
            .map_err(|e| GpuError::ReadBack(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::groups_1d;

    #[test]
    fn launches_cover_n_and_respect_the_per_dimension_limit() {
        for n in [0usize, 1, 63, 64, 65, 64 * 65_535, 64 * 65_535 + 1, 1 << 24, (1 << 26) + 17] {
            let g = groups_1d(n, 64);
            assert!(g[0] <= 65_535 && g[1] <= 65_535, "{n}: {g:?}");
            assert!(g[0] as u64 * g[1] as u64 * 64 >= n as u64, "{n}: {g:?}");
            assert!(g[0] >= 1);
        }
    }
}
