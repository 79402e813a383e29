//! The coordinator's web page: the job list with progress, noise and previews, refreshed every two
//! seconds, a submit form, and the workers. Plain HTML and JavaScript against the REST API; the token
//! (if the farm has one) is kept in the browser's localStorage.

pub const PAGE: &str = r##"<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Tessera</title>
<style>
body{font:14px system-ui,sans-serif;margin:2em;max-width:1100px;color:#222}
table{border-collapse:collapse;width:100%}td,th{padding:4px 8px;border-bottom:1px solid #ddd;text-align:left}
.bar{background:#eee;width:160px;height:10px}.bar div{background:#3a7;height:10px}
img{max-width:160px;image-rendering:pixelated}input,select{margin-right:6px}
.err{color:#b00} .warn{color:#a60}
</style></head><body>
<h1>Tessera render farm</h1>
<p>Token: <input id="token" type="password" placeholder="TESSERA_TOKEN (if set)"> <span id="msg" class="err"></span></p>
<form id="submit"><b>Submit</b>
 <input type="file" name="scene" multiple required>
 spp <input name="spp" type="number" placeholder="64" min="1" style="width:6em">
 noise target <input name="noise_target" type="number" step="any" placeholder="e.g. 0.02" style="width:6em">
 time budget <input name="time_budget" type="number" step="any" placeholder="s" style="width:5em">
 width <input name="width" type="number" placeholder="auto" style="width:6em">
 frames <input name="frames" placeholder="e.g. 1-240" style="width:6em">
 <select name="integrator"><option>mis</option><option>nee</option><option>bsdf</option></select>
 priority <input name="priority" type="number" value="0" style="width:4em">
 <button>Submit</button></form>
<h2>Jobs</h2><table id="jobs"><tr><th>job</th><th>state</th><th>progress</th><th>elapsed / ETA</th><th>rel. error</th><th>spp</th><th>preview</th><th></th></tr></table>
<h2>Workers</h2><table id="workers"><tr><th>id</th><th>name</th><th>cores</th><th>units done</th><th>rejected</th><th>last seen</th><th>state</th><th>job</th><th></th></tr></table>
<script>
const tok = document.getElementById('token');
tok.value = localStorage.getItem('tessera-token') || '';
tok.onchange = () => localStorage.setItem('tessera-token', tok.value);
const hdr = () => tok.value ? {Authorization: 'Bearer ' + tok.value} : {};
const msg = t => document.getElementById('msg').textContent = t || '';
const esc = s => String(s ?? '').replace(/[&<>"]/g, c => ({'&':'&amp;','<':'&lt;','>':'&gt;','"':'&quot;'}[c]));
async function api(path, opts={}) {
  const r = await fetch('/api/v1' + path, {...opts, headers: {...hdr(), ...(opts.headers||{})}});
  if (!r.ok) { let e = r.status; try { e = (await r.json()).error } catch {} throw new Error(e); }
  return r;
}
// A shot (several frames): frames done and running, each frame's state, the latest frame's preview.
function shotRow(j) {
  const fj = j.frame_jobs || [];
  const shown = [...fj].reverse().find(f => f.state === 'done' || (f.progress || 0) > 0);
  const frames = fj.map(f => `<span title="frame ${f.frame}: ${esc(f.state)}, rel. error ${f.estimated_rel_error?.toExponential(2) ?? '-'}">${f.frame}:${f.state === 'done' ? 'done' : (100 * (f.progress || 0)).toFixed(0) + '%'}</span>`).join(' ');
  return `<tr><td>${esc(j.id)}<br><small>${esc(j.name)} (frames ${j.frames.first}-${j.frames.last})</small>${(j.warnings || []).map(w => '<br><small class=warn>warning: ' + esc(w) + '</small>').join('')}</td><td>${esc(j.state)}</td>
    <td><div class=bar><div style="width:${(100*j.progress.fraction).toFixed(1)}%"></div></div>${j.frames.done}/${j.frames.count} frames, ${j.frames.running} running</td>
    <td>${j.elapsed_s?.toFixed(1) ?? '-'} s / ${j.eta_s?.toFixed(0) ?? '-'} s</td>
    <td>worst frame ${j.noise.worst_frame_rel_error?.toExponential(2) ?? '-'}</td>
    <td><small>${frames}</small></td>
    <td>${shown ? `<img data-src="/api/v1/jobs/${esc(shown.id)}/preview.png">` : ''}</td>
    <td>${j.frames.done ? `<a href="#" data-tar="${esc(j.id)}">frames.tar</a> ` : ''}${['queued','running'].includes(j.state) ? `<a href="#" data-cancel="${esc(j.id)}">cancel</a>` : ''}</td></tr>`;
}
async function refresh() {
  try {
    const jobs = (await (await api('/jobs')).json()).jobs.reverse();
    document.getElementById('jobs').innerHTML = '<tr><th>job</th><th>state</th><th>progress</th><th>elapsed / ETA</th><th>rel. error</th><th>spp</th><th>preview</th><th></th></tr>' +
      jobs.map(j => j.kind === 'shot' ? shotRow(j) : `<tr><td>${esc(j.id)}<br><small>${esc(j.name)}</small>${(j.warnings || []).map(w => '<br><small class=warn>warning: ' + esc(w) + '</small>').join('')}</td><td>${esc(j.state)}${j.error ? '<br><span class=err>' + esc(j.error) + '</span>' : ''}</td>
      <td><div class=bar><div style="width:${(100*j.progress.fraction).toFixed(1)}%"></div></div>${j.progress.units_done}/${j.progress.units_total} units</td>
      <td>${j.elapsed_s?.toFixed(1) ?? '-'} s / ${j.eta_s?.toFixed(0) ?? '-'} s</td>
      <td>${j.noise.estimated_rel_error?.toExponential(2) ?? '-'}${j.budget.noise_target ? ' / target ' + j.budget.noise_target : ''}</td>
      <td>${j.progress.spp_min ?? 0}${j.progress.spp_max !== j.progress.spp_min ? '..' + j.progress.spp_max : ''}<br><small>${esc(j.budget.stop)}${j.budget.time_budget_s ? ', budget ' + j.budget.time_budget_s + ' s' : ''}</small></td>
      <td><img data-src="/api/v1/jobs/${esc(j.id)}/preview.png"></td>
      <td>${j.state === 'done' ? `<a href="#" data-dl="${esc(j.id)}">EXR</a>` : (['queued','running'].includes(j.state) ? `<a href="#" data-cancel="${esc(j.id)}">cancel</a>` : '')}</td></tr>`).join('');
    for (const img of document.querySelectorAll('img[data-src]')) {
      const r = await api(img.dataset.src.replace('/api/v1', ''));
      img.src = URL.createObjectURL(await r.blob());
    }
    const ws = (await (await api('/workers')).json()).workers;
    document.getElementById('workers').innerHTML = '<tr><th>id</th><th>name</th><th>cores</th><th>units done</th><th>rejected</th><th>last seen</th><th>state</th><th>job</th><th></th></tr>' +
      ws.map(w => `<tr><td>${esc(w.id)}</td><td>${esc(w.name)}</td><td>${w.cores}</td><td>${w.units_done}</td><td>${w.units_rejected}</td><td>${w.seconds_since_seen.toFixed(0)} s ago</td><td>${esc(w.state)}</td><td>${esc(w.current_job ?? '-')}</td><td><a href="#" data-${w.draining ? 'resume' : 'drain'}="${esc(w.id)}">${w.draining ? 'resume' : 'drain'}</a></td></tr>`).join('');
    msg('');
  } catch (e) { msg(e.message); }
}
document.addEventListener('click', async e => {
  const t = e.target;
  try {
    if (t.dataset.drain || t.dataset.resume) { e.preventDefault();
      await api('/workers/' + (t.dataset.drain || t.dataset.resume) + (t.dataset.drain ? '/drain' : '/resume'), {method: 'POST'}); refresh(); }
    if (t.dataset.cancel) { e.preventDefault(); await api('/jobs/' + t.dataset.cancel + '/cancel', {method: 'POST'}); refresh(); }
    if (t.dataset.dl) { e.preventDefault(); const b = await (await api('/jobs/' + t.dataset.dl + '/image.exr')).blob();
      const a = document.createElement('a'); a.href = URL.createObjectURL(b); a.download = t.dataset.dl + '.exr'; a.click(); }
    if (t.dataset.tar) { e.preventDefault(); const b = await (await api('/jobs/' + t.dataset.tar + '/frames.tar')).blob();
      const a = document.createElement('a'); a.href = URL.createObjectURL(b); a.download = t.dataset.tar + '-frames.tar'; a.click(); }
  } catch (err) { msg(err.message); }
});
document.getElementById('submit').onsubmit = async e => {
  e.preventDefault();
  const f = e.target, fd = new FormData();
  for (const file of f.scene.files) fd.append('scene', file, file.name);
  const s = {integrator: f.integrator.value, priority: +f.priority.value};
  if (f.spp.value) s.spp = +f.spp.value;
  if (f.width.value) s.width = +f.width.value;
  if (f.noise_target.value) s.noise_target = +f.noise_target.value;
  if (f.time_budget.value) s.time_budget = +f.time_budget.value;
  if (f.frames.value) s.frames = f.frames.value;
  fd.append('settings', JSON.stringify(s));
  try { await api('/jobs', {method: 'POST', body: fd}); refresh(); } catch (err) { msg(err.message); }
};
refresh(); setInterval(refresh, 2000);
</script></body></html>
"##;
