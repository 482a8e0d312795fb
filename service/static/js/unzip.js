// Reading members of a zip in the browser: a GLB bake with a height map or a GPU texture
// comes back as a zip of <stem>.glb and those files, and "View in 3D" needs the GLB.
// Stored and deflated members (what the service writes); no zip64, no encryption.

const END_OF_DIRECTORY = 0x06054b50;
const DIRECTORY_ENTRY = 0x02014b50;
const LOCAL_HEADER = 0x04034b50;

/** Whether the bytes start like a zip (a local file header: "PK\x03\x04"). */
export function isZip(buffer) {
  return buffer.byteLength >= 4 && new DataView(buffer).getUint32(0, true) === LOCAL_HEADER;
}

/** The members of a zip: [{name, method, offset, size}] from its central directory. */
export function zipEntries(buffer) {
  const view = new DataView(buffer);
  let end = -1;
  // the end record is 22 bytes plus a comment of at most 65535
  for (let at = buffer.byteLength - 22; at >= Math.max(0, buffer.byteLength - 22 - 65535); at -= 1) {
    if (view.getUint32(at, true) === END_OF_DIRECTORY) { end = at; break; }
  }
  if (end < 0) throw new Error('not a zip file (no end of central directory)');
  const count = view.getUint16(end + 10, true);
  let at = view.getUint32(end + 16, true);
  const names = new TextDecoder();
  const entries = [];
  for (let i = 0; i < count; i += 1) {
    if (view.getUint32(at, true) !== DIRECTORY_ENTRY) throw new Error('broken zip central directory');
    const nameLength = view.getUint16(at + 28, true);
    entries.push({
      method: view.getUint16(at + 10, true),
      size: view.getUint32(at + 20, true), // compressed
      offset: view.getUint32(at + 42, true),
      name: names.decode(new Uint8Array(buffer, at + 46, nameLength)),
    });
    at += 46 + nameLength + view.getUint16(at + 30, true) + view.getUint16(at + 32, true);
  }
  return entries;
}

/** The bytes (ArrayBuffer) of one member, inflated with the browser's DecompressionStream. */
export async function zipMember(buffer, entry) {
  const view = new DataView(buffer);
  if (view.getUint32(entry.offset, true) !== LOCAL_HEADER) throw new Error(`broken zip member ${entry.name}`);
  const start = entry.offset + 30 + view.getUint16(entry.offset + 26, true) + view.getUint16(entry.offset + 28, true);
  const data = new Uint8Array(buffer, start, entry.size);
  if (entry.method === 0) return data.slice().buffer;
  if (entry.method !== 8) throw new Error(`zip member ${entry.name} uses compression method ${entry.method}`);
  const stream = new Blob([data]).stream().pipeThrough(new DecompressionStream('deflate-raw'));
  return new Response(stream).arrayBuffer();
}

/** The first member whose name ends in ``suffix`` (e.g. '.glb'), or throws saying so. */
export async function zipMemberEndingIn(buffer, suffix) {
  const entry = zipEntries(buffer).find((e) => e.name.toLowerCase().endsWith(suffix));
  if (!entry) throw new Error(`the zip holds no ${suffix} file`);
  return zipMember(buffer, entry);
}
