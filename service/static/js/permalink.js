// The view in the URL hash (#t=ID&seed=1&plane=xy&offset=0&z=6&x=12.5&y=-3), so a
// view can be bookmarked or shared and survives a reload.

const KEYS = ['t', 'seed', 'plane', 'offset', 'z', 'x', 'y'];

/**
 * The hash's view, or null without a texture id. Numbers are parsed; absent ones undefined,
 * and so is a plane not among `planes` (the server's, GET /v1/limits).
 */
export function readView(planes, hash = window.location.hash) {
  const params = new URLSearchParams(hash.replace(/^#/, ''));
  if (!params.get('t')) return null;
  const number = (key) => (params.has(key) && Number.isFinite(Number(params.get(key))) ? Number(params.get(key)) : undefined);
  const plane = planes.includes(params.get('plane')) ? params.get('plane') : undefined;
  return { t: params.get('t'), seed: number('seed'), plane, offset: number('offset'), z: number('z'), x: number('x'), y: number('y') };
}

/** Replace the hash (no history entry per pan step). */
export function writeView(view) {
  const params = new URLSearchParams();
  for (const key of KEYS) {
    if (view[key] !== undefined && view[key] !== null) params.set(key, view[key]);
  }
  window.history.replaceState(null, '', `#${params}`);
}
