//! Tiny glTF files built by hand for the loader tests and the glTF fuzz
//! smoke test: a GLB container (JSON chunk + binary chunk), its buffer, and
//! a document exercising meshes, primitive modes, materials and a node
//! hierarchy.

/// A GLB file: header, JSON chunk (padded with spaces) and, when `bin` is
/// not empty, a binary chunk (padded with zeros).
pub fn glb(json: &str, bin: &[u8]) -> Vec<u8> {
    glb_bytes(json.as_bytes(), bin)
}

/// [`glb`] of a JSON chunk given as bytes (the fuzz test's mutated JSON,
/// which need not be UTF-8).
pub fn glb_bytes(json: &[u8], bin: &[u8]) -> Vec<u8> {
    let mut j = json.to_vec();
    while !j.len().is_multiple_of(4) {
        j.push(b' ');
    }
    let mut b = bin.to_vec();
    while !b.len().is_multiple_of(4) {
        b.push(0);
    }
    let total = 12 + 8 + j.len() + if b.is_empty() { 0 } else { 8 + b.len() };
    let mut out = Vec::with_capacity(total);
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((j.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(j);
    if !b.is_empty() {
        out.extend((b.len() as u32).to_le_bytes());
        out.extend(b"BIN\0");
        out.extend(b);
    }
    out
}

/// Buffer: 4 positions (48 bytes), then 3 u16 indices (6 bytes, padded to 8).
pub fn glb_buffer(positions: &[[f32; 3]; 4], indices: [u16; 3]) -> Vec<u8> {
    let mut b = Vec::new();
    for p in positions {
        for c in p {
            b.extend(c.to_le_bytes());
        }
    }
    for i in indices {
        b.extend(i.to_le_bytes());
    }
    b.extend([0, 0]);
    b
}

pub const QUAD: [[f32; 3]; 4] = [[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [1., 1., 0.]];

/// Mesh 0: an indexed triangle (two primitives: triangles + points).
/// Mesh 1: a non-indexed triangle strip over 4 vertices (2 triangles).
/// Nodes: 0 root (translate x 10; children 1, 2), 1 (scale 2,1,1; mesh 0),
/// 2 (rotate 90 degrees about z; child 3), 3 (translate y 5; mesh 1), 4 (not
/// in the scene; mesh 0).
pub fn tiny_gltf_json(index_count: u32, node0_extra: &str, pos_min: &str) -> String {
    format!(
        r#"{{
  "asset": {{"version": "2.0"}},
  "buffers": [{{"byteLength": 56}}],
  "bufferViews": [
    {{"buffer": 0, "byteOffset": 0, "byteLength": 48}},
    {{"buffer": 0, "byteOffset": 48, "byteLength": 6}}
  ],
  "accessors": [
    {{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": {pos_min}, "max": [1, 1, 0]}},
    {{"bufferView": 1, "componentType": 5123, "count": {index_count}, "type": "SCALAR"}}
  ],
  "materials": [{{"name": "steel"}}, {{"name": "brass"}}],
  "meshes": [
    {{"name": "tri", "primitives": [
      {{"attributes": {{"POSITION": 0}}, "indices": 1, "material": 0}},
      {{"attributes": {{"POSITION": 0}}, "mode": 0, "material": 1}}
    ]}},
    {{"name": "strip", "primitives": [{{"attributes": {{"POSITION": 0}}, "mode": 5, "material": 1}}]}}
  ],
  "nodes": [
    {{"name": "root", "translation": [10, 0, 0], "children": [1, 2]{node0_extra}}},
    {{"name": "stretched", "scale": [2, 1, 1], "mesh": 0}},
    {{"name": "turned", "rotation": [0, 0, 0.70710677, 0.70710677], "children": [3]}},
    {{"name": "lifted", "translation": [0, 5, 0], "mesh": 1}},
    {{"name": "orphan", "mesh": 0}}
  ],
  "scenes": [{{"nodes": [0]}}],
  "scene": 0
}}"#
    )
}

/// Standard base64 with padding, for `data:` URIs.
pub fn base64(bytes: &[u8]) -> String {
    const ABC: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ABC[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// [`tiny_gltf_json`]'s document as a `.gltf` file: the buffer embedded as
/// a `data:` URI (so it loads without a base directory or a GLB chunk).
pub fn tiny_gltf_embedded() -> String {
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64(&glb_buffer(&QUAD, [0, 1, 2]))
    );
    let json = tiny_gltf_json(3, "", "[0, 0, 0]");
    let embedded = json.replace(
        r#""buffers": [{"byteLength": 56}]"#,
        &format!(r#""buffers": [{{"byteLength": 56, "uri": "{uri}"}}]"#),
    );
    assert_ne!(
        embedded, json,
        "the buffer entry to embed is where expected"
    );
    embedded
}
