//! A plain-WGSL emulation of wgpu's cooperative-matrix operations, so kernels written for tensor
//! cores run (slowly) on any adapter with f16, e.g. lavapipe. Semantics (those under which
//! `linear_coop.wgsl` and `mlp_fused_coop.wgsl` were checked on an H100, and which
//! `tests/linear.rs` and `tests/mlp_coop.rs` re-check through this emulation): a 16×16 matrix is
//! `m[r·16 + c]`; `coopLoadT(&a[i], st)` reads row-major (`a[i + r·st + c]`), `coopLoad(&a[i], st)`
//! column-major (`a[i + c·st + r]`), `coopStoreT` writes row-major, `coopMultiplyAdd(a, b, c) =
//! a·b + c` with each entry summed over k = 0..16 in order, in f32.
//!
//! Each matrix is spread over its subgroup's 32 lanes as on the hardware: lane `l` holds entries
//! `8l .. 8l + 8` of `m[r·16 + c]` (row `l / 2`, columns `8·(l % 2) ..`) in an `array<f32, 8>`, so
//! loads and stores move 8 entries per lane. A multiply-add passes A, then B, through 256 f16 of
//! workgroup memory per subgroup (`emu_ab`: 2 KiB, enough for workgroups of 4 subgroups; the
//! operands are f16 values, so the round trip is exact) between workgroup barriers, and each lane
//! sums its 8 entries. An earlier form did every whole operation on lane 0 of the subgroup
//! (`array<f32, 256>` per matrix): lavapipe compiled it so slowly that one test of the 64×64 tiled
//! GEMMs took 10 minutes, against 18 s in this form.
//!
//! Requirements on the shader: every entry point with cooperative-matrix operations starts with
//! `let n = load_n(lid);`, takes its subgroups as consecutive runs of 32 invocations (`lid / 32`,
//! as on the H100), keeps every cooperative-matrix operation in workgroup-uniform control flow (the
//! hardware needs subgroup-uniform; the emulated multiply-add has barriers), has `enable f16;`,
//! leaves 2 KiB of workgroup memory free, and names each coop pointer as `&ARRAY[INDEX]`.

pub fn emulate(source: &str) -> String {
    const MAT: &str = "array<f32, 8>";
    // Without comments (they name the coop ops too).
    let src: String = source
        .lines()
        .map(|l| format!("{}\n", l.split("//").next().unwrap_or("")))
        .collect();
    let src = src.replace("enable wgpu_cooperative_matrix;\n", "");
    assert!(!src.contains("wgpu_cooperative_matrix"));
    assert!(src.contains("enable f16;"), "the emulated multiply-add stages f16 tiles");
    let src = src
        .replace("coop_mat16x16<f32, C>()", &format!("{MAT}()"))
        .replace("coop_mat16x16<f16, A>()", &format!("{MAT}()"))
        .replace("coop_mat16x16<f16, B>()", &format!("{MAT}()"))
        .replace("coopMultiplyAdd(", "emu_mma(");
    // Each entry point with coop ops starts with `let n = load_n(lid);`: record the lane within
    // its subgroup of 32 and the subgroup within the workgroup.
    let src = {
        let marker = "let n = load_n(lid);";
        let (mut out, mut last) = (String::new(), 0);
        for (at, _) in src.match_indices(marker) {
            let size_at = src[..at].rfind("@workgroup_size(").expect("an entry point with coop ops has a @workgroup_size") + 16;
            let size = src[size_at..].split(')').next().unwrap_or("").trim();
            let (lane, sg) = if size == "32" || size == "32u" { ("lid", "0u") } else { ("lid % 32u", "lid / 32u") };
            out.push_str(&src[last..at]);
            out.push_str(&format!("emu_lane = {lane};\n    emu_sg = {sg};\n    {marker}"));
            last = at + marker.len();
        }
        out.push_str(&src[last..]);
        out
    };
    // This lane's 8 entries: j = 0..8 is row r = lane / 2, column c = 8·(lane % 2) + j.
    let lane_entries = "for (var j = 0u; j < 8u; j++) {\n        let r = emu_lane / 2u;\n        let c = 8u * (emu_lane % 2u) + j;\n        ";
    let mut out = String::new();
    let mut funcs = std::collections::BTreeMap::new();
    let mut rest = src.as_str();
    // Loads: coopLoad[T]<coop_mat16x16<f16, R>>(&ARRAY[INDEX], STRIDE)
    while let Some(at) = rest.find("coopLoad") {
        out.push_str(&rest[..at]);
        let tail = &rest[at..];
        let row_major = tail.starts_with("coopLoadT<");
        let args_at = tail.find(">>(").expect("coop load type arguments") + 3;
        let (close, args) = call_args(tail, args_at);
        assert_eq!(args.len(), 2, "coop load: two arguments");
        let (ptr, stride) = (args[0], args[1]);
        let ptr = ptr.strip_prefix('&').expect("coop load: a pointer");
        let (array, index) = ptr.strip_suffix(']').and_then(|p| p.split_once('[')).expect("coop load: &array[index]");
        let name = format!("emu_load_{}_{array}", if row_major { "rm" } else { "cm" });
        let elem = if row_major { "i + r * st + c" } else { "i + c * st + r" };
        funcs.entry(name.clone()).or_insert(format!(
            "fn {name}(i: u32, st: u32) -> {MAT} {{\n    var m = {MAT}();\n    {lane_entries}m[j] = f32({array}[{elem}]);\n    }}\n    return m;\n}}\n"
        ));
        out.push_str(&format!("{name}({index}, {stride})"));
        rest = &tail[close + 1..];
    }
    out.push_str(rest);
    // Stores: coopStoreT(MATRIX, &ARRAY[INDEX], STRIDE);
    let src = out;
    let mut out = String::new();
    let mut rest = src.as_str();
    while let Some(at) = rest.find("coopStoreT(") {
        out.push_str(&rest[..at]);
        let tail = &rest[at + "coopStoreT(".len()..];
        let (close, parts) = call_args(tail, 0);
        assert_eq!(parts.len(), 3, "coop store: {}", &tail[..close]);
        let ptr = parts[1].strip_prefix('&').expect("coop store: a pointer");
        let (array, index) = ptr.strip_suffix(']').and_then(|p| p.split_once('[')).expect("coop store: &array[index]");
        let name = format!("emu_store_{array}");
        funcs.entry(name.clone()).or_insert(format!(
            "fn {name}(m: {MAT}, i: u32, st: u32) {{\n    {lane_entries}{array}[i + r * st + c] = m[j];\n    }}\n}}\n"
        ));
        out.push_str(&format!("{name}({}, {index}, {})", parts[0], parts[2]));
        rest = &tail[close + 1..];
    }
    out.push_str(rest);
    for op in ["coopLoad", "coopStore", "coopMultiplyAdd", "coop_mat"] {
        assert!(!out.contains(op), "an unemulated {op} is left");
    }
    // The multiply-add: row emu_lane / 2 of A (its 16 k) from emu_ab, then column
    // 8·(lane % 2) + j of B, each lane summing its 8 entries of C over k in order.
    out.push_str(
        "\nvar<private> emu_lane: u32;\n\
         var<private> emu_sg: u32;\n\
         var<workgroup> emu_ab: array<f16, 1024>;\n\
         fn emu_mma(a: array<f32, 8>, b: array<f32, 8>, c_in: array<f32, 8>) -> array<f32, 8> {\n\
         \x20   let o = emu_sg * 256u;\n    let r = emu_lane / 2u;\n    let c0 = 8u * (emu_lane % 2u);\n\
         \x20   for (var j = 0u; j < 8u; j++) { emu_ab[o + 8u * emu_lane + j] = f16(a[j]); }\n    workgroupBarrier();\n\
         \x20   var ar = array<f32, 16>();\n    for (var k = 0u; k < 16u; k++) { ar[k] = f32(emu_ab[o + r * 16u + k]); }\n    workgroupBarrier();\n\
         \x20   for (var j = 0u; j < 8u; j++) { emu_ab[o + 8u * emu_lane + j] = f16(b[j]); }\n    workgroupBarrier();\n\
         \x20   var d = c_in;\n\
         \x20   for (var j = 0u; j < 8u; j++) {\n        var s = d[j];\n\
         \x20       for (var k = 0u; k < 16u; k++) { s += ar[k] * f32(emu_ab[o + k * 16u + c0 + j]); }\n        d[j] = s;\n    }\n\
         \x20   workgroupBarrier();\n    return d;\n}\n",
    );
    for f in funcs.values() {
        out.push_str(f);
    }
    out
}

/// The arguments of a call whose argument list starts at `tail[start..]` (just after its `(`):
/// (index of the closing `)`, the top-level comma-separated arguments, trimmed).
fn call_args(tail: &str, start: usize) -> (usize, Vec<&str>) {
    let (mut depth, mut args, mut from) = (0i32, Vec::new(), start);
    for (i, ch) in tail[start..].char_indices() {
        let i = start + i;
        match ch {
            '(' | '[' => depth += 1,
            ')' | ']' if depth > 0 => depth -= 1,
            ')' => {
                args.push(tail[from..i].trim());
                return (i, args);
            }
            ',' if depth == 0 => {
                args.push(tail[from..i].trim());
                from = i + 1;
            }
            _ => {}
        }
    }
    panic!("unbalanced call: {}", &tail[start..tail.len().min(start + 80)]);
}
