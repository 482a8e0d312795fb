// Live job progress: one list item per job, fed by the job's server-sent events;
// falls back to polling GET /v1/jobs/{id} if the event stream breaks. With an API key
// the events are read with fetch (EventSource cannot send the X-API-Key header) and the
// download link fetches the result with the key.
import {
  cancelJob, downloadWithKey, getJob, hasApiKey, jobEventsUrl, jobResultUrl, streamEvents,
} from './api.js';

/** The states a job ends in (JobState in service/vocabulary.py). */
export const TERMINAL = new Set(['succeeded', 'failed', 'canceled']);
// GET /v1/jobs/{id}/events sends `progress` ({state, progress, attempt}) while the job
// runs, then one last event named after the end state carrying the whole job.
const EVENT_NAMES = ['progress', 'succeeded', 'failed', 'canceled'];

/** Progress as a 0..1 fraction whether the server reports 0..1 or 0..100. */
export function fraction(progress) {
  const p = Number(progress) || 0;
  return Math.max(0, Math.min(1, p > 1 ? p / 100 : p));
}

/** What a job makes, e.g. "bake sphere.obj (glb)", "volume 64^3 (npy)", "fit 90 s". */
function what(job) {
  const p = job.params || {};
  if (job.kind === 'bake') return `bake ${p.filename || 'mesh'} (${p.format || 'glb'})`;
  if (job.kind === 'volume') return `volume ${p.resolution}^3 (${p.format})`;
  if (job.kind === 'fit') return p.in_place ? 'refine' : `fit ${p.seconds ?? ''} s`;
  if (job.kind === 'region') return `${p.tileable ? 'tileable' : 'region'} ${p.width}x${p.height} (${p.format})`;
  return `${job.kind || 'job'} ${job.id.slice(0, 8)}`;
}

/**
 * A short label for a job naming its texture, e.g. "bake sphere.obj (glb) · brick".
 * `nameOf(textureId)`: the texture's name, if known (else the id's first 8 characters).
 */
export function describe(job, nameOf = () => null) {
  if (!job.texture_id) return what(job);
  return `${what(job)} · ${nameOf(job.texture_id) || job.texture_id.slice(0, 8)}${samplerNote(job.sampler)}`;
}

/**
 * What a job renders with, when its texture's refinement may still change it (job.sampler):
 * " (waits for the refinement)", " (encoder: before the refinement)", " (interim: ...)"; else ''.
 */
export function samplerNote(sampler) {
  if (!sampler) return '';
  if (sampler.waiting_for_refinement) return ' (waits for the refinement)';
  if (sampler.refining) return ` (${sampler.kind}: before the refinement)`;
  return '';
}

/**
 * Follow a job until it ends: `onState(state)` with every update (a JobOut, or the
 * `{state, progress, attempt}` of a progress event), the last one a terminal state.
 * Server-sent events (EventSource, or read with fetch while an API key is set), polling
 * GET /v1/jobs/{id} once the stream breaks. `onError(error)`: polling got a 401 and
 * stopped (retrying cannot help). Returns a function that stops following.
 * @param {{id: string, state?: string}} job
 */
export function follow(job, onState, { onError = () => {} } = {}) {
  let finished = false;
  let stopped = false;
  let stopStream = () => {};
  const update = (state) => {
    if (finished || stopped || !state) return;
    if (TERMINAL.has(state.state || state.status)) { finished = true; stopStream(); }
    onState(state);
  };
  const stop = () => { stopped = true; stopStream(); };

  const poll = async () => {
    while (!finished && !stopped) {
      try {
        update(await getJob(job.id));
      } catch (error) {
        // No (valid) API key: retrying cannot help; other errors are transient.
        if (error.status === 401) { onError(error); return; }
      }
      await new Promise((resolve) => setTimeout(resolve, 1000));
    }
  };
  const onEvent = (event) => {
    let data;
    try { data = JSON.parse(event.data); } catch { return; }
    update(data.job || data);
  };

  if (TERMINAL.has(job.state)) {
    update(job);
    return stop;
  }
  if (hasApiKey()) {
    const controller = new AbortController();
    stopStream = () => controller.abort();
    streamEvents(jobEventsUrl(job.id), onEvent, { signal: controller.signal })
      .catch(() => {}) // network error or HTTP error: poll instead
      .then(() => { if (!finished && !stopped) poll(); }); // ended early: poll
    return stop;
  }
  const source = new EventSource(jobEventsUrl(job.id));
  stopStream = () => source.close();
  source.onmessage = onEvent;
  for (const name of EVENT_NAMES) source.addEventListener(name, onEvent);
  source.onerror = () => {
    // The server closes the stream after the last event; EventSource would reconnect.
    source.close();
    if (!finished && !stopped) poll();
  };
  return stop;
}

export class JobList {
  /**
   * @param {HTMLElement} list  the <ul> to fill
   * @param {{nameOf?: (textureId: string) => string | null}} options  labels name the texture
   */
  constructor(list, { nameOf = () => null } = {}) {
    this.list = list;
    this.nameOf = nameOf;
    this.stops = new Set(); // stop functions of the jobs being followed
  }

  /** Drop the jobs of a deleted texture (the server deleted them with it). */
  forgetTexture(textureId) {
    for (const item of [...this.list.children]) {
      if (item.dataset.textureId !== textureId) continue;
      item._stop?.();
      this.stops.delete(item._stop);
      item.remove();
    }
  }

  /** Stop following every job and empty the list (e.g. when the API key changes). */
  clear() {
    for (const stop of this.stops) stop();
    this.stops.clear();
    this.list.replaceChildren();
  }

  /**
   * List a job and follow it until it ends.
   * @param {object} job  a JobOut (the 202 body of a submission, or from GET /v1/jobs)
   * @param {{label?: string, onSuccess?: (job: object, resultUrl: string) => void,
   *          onState?: (state: object) => void, onView?: (resultUrl: string) => void}} options
   *   onState: every update (a JobOut, or a progress event's {state, progress, attempt}).
   *   onView: offered as a "View in 3D" button on finished GLB bakes.
   */
  track(job, { label = describe(job, this.nameOf), onSuccess = () => {}, onState = () => {}, onView = null } = {}) {
    const item = document.createElement('li');
    item.dataset.jobId = job.id;
    if (job.texture_id) item.dataset.textureId = job.texture_id;
    item.innerHTML = `<div><strong></strong> <span class="state">queued</span></div>
      <progress max="1" value="0"></progress>
      <div class="links"><button type="button" class="cancel">Cancel</button></div>`;
    item.querySelector('strong').textContent = label;
    item.querySelector('progress').setAttribute('aria-label', `Progress of ${label}`);
    const cancel = item.querySelector('.cancel');
    cancel.setAttribute('aria-label', `Cancel ${label}`);
    this.list.prepend(item);

    let stop = () => {};
    const show = (state) => {
      const status = state.state || state.status || 'running';
      item.dataset.state = status;
      item.querySelector('.state').textContent = status;
      item.querySelector('progress').value = status === 'succeeded' ? 1 : fraction(state.progress);
      onState(state);
      if (!TERMINAL.has(status)) return;
      this.stops.delete(stop);
      cancel.remove();
      if (status === 'succeeded') {
        const url = jobResultUrl(job.id);
        const link = document.createElement('a');
        link.href = url;
        link.textContent = 'Download result';
        link.setAttribute('download', '');
        if (hasApiKey()) {
          // A plain link cannot send the key: fetch the file with it, then save the blob.
          link.addEventListener('click', async (event) => {
            event.preventDefault();
            try { await downloadWithKey(url, `${job.id}.bin`); } catch (error) { link.title = error.message; }
          });
        }
        item.querySelector('.links').append(link);
        if (onView && job.kind === 'bake' && job.params?.format === 'glb') {
          const view = document.createElement('button');
          view.type = 'button';
          view.textContent = 'View in 3D';
          view.addEventListener('click', () => onView(url));
          item.querySelector('.links').append(' ', view);
        }
        onSuccess(state, url);
      } else {
        const error = state.error && (state.error.detail || state.error.message || state.error);
        item.querySelector('.state').classList.add('failed');
        item.querySelector('.state').textContent = `${status}${error ? `: ${error}` : ''}`;
      }
    };
    stop = follow(job, show, {
      onError: () => { item.querySelector('.state').textContent = 'needs an API key'; },
    });
    item._stop = stop;
    if (TERMINAL.has(item.dataset.state)) return; // it had ended already
    this.stops.add(stop);
    cancel.addEventListener('click', async () => {
      cancel.disabled = true;
      try {
        const state = await cancelJob(job.id); // a queued job is canceled at once
        if (TERMINAL.has(state.state)) { stop(); show(state); }
      } catch {
        cancel.disabled = false;
      }
    });
  }
}
