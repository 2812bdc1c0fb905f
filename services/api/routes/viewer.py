"""GET /: a self-contained live viewer (no CDN: the page must work offline)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

router = APIRouter()

PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>HiveMap</title>
<style>
 body{margin:0;font:14px system-ui,sans-serif;background:#111;color:#ddd}
 header{padding:8px 12px;background:#1b1b1b;display:flex;gap:16px;align-items:baseline}
 h1{font-size:16px;margin:0} #status{color:#8a8} canvas{display:block}
 #legend span{margin-right:12px}
</style></head>
<body><header><h1>HiveMap</h1><span id="status">connecting…</span><span id="legend"></span></header>
<canvas id="c"></canvas>
<script>
const cv=document.getElementById('c'),cx=cv.getContext('2d');
const colors=['#e6194b','#3cb44b','#4363d8','#f58231','#911eb4','#42d4f4','#f032e6','#bfef45'];
const agents={}; let view={cx:0,cy:0,s:30};
function color(a){const k=Object.keys(agents).sort();return colors[k.indexOf(a)%colors.length];}
function resize(){cv.width=innerWidth;cv.height=innerHeight-40;}
addEventListener('resize',resize);resize();
async function poll(){
  try{
    const list=await (await fetch('agents')).json();
    for(const a of list){
      const t=await (await fetch('agents/'+encodeURIComponent(a.agent)+'/trajectory?format=json')).json();
      agents[a.agent]=Object.assign(agents[a.agent]||{}, {traj:t.keyframes.map(k=>k.position), map:a.map_id});
      if(a.last_pose) agents[a.agent].pose=a.last_pose.position;
    }
    document.getElementById('legend').innerHTML=Object.keys(agents).sort().map(
      a=>`<span style="color:${color(a)}">■ ${a} (${agents[a].map}, ${agents[a].traj.length} KFs)</span>`).join('');
  }catch(e){document.getElementById('status').textContent='api unreachable';}
  setTimeout(poll,3000);
}
function fit(){
  const pts=[];for(const a in agents){pts.push(...(agents[a].traj||[]));if(agents[a].pose)pts.push(agents[a].pose);}
  if(!pts.length)return;
  let x0=Math.min(...pts.map(p=>p[0])),x1=Math.max(...pts.map(p=>p[0]));
  let y0=Math.min(...pts.map(p=>p[1])),y1=Math.max(...pts.map(p=>p[1]));
  view.cx=(x0+x1)/2;view.cy=(y0+y1)/2;view.s=0.9*Math.min(cv.width/Math.max(x1-x0,1),cv.height/Math.max(y1-y0,1));
}
function px(p){return [cv.width/2+(p[0]-view.cx)*view.s, cv.height/2-(p[1]-view.cy)*view.s];}
function draw(){
  fit();cx.fillStyle='#111';cx.fillRect(0,0,cv.width,cv.height);
  for(const a in agents){
    const g=agents[a];cx.strokeStyle=color(a);cx.lineWidth=1.5;cx.beginPath();
    (g.traj||[]).forEach((p,i)=>{const q=px(p);i?cx.lineTo(q[0],q[1]):cx.moveTo(q[0],q[1]);});cx.stroke();
    if(g.pose){const q=px(g.pose);cx.fillStyle=color(a);cx.beginPath();cx.arc(q[0],q[1],5,0,7);cx.fill();}
  }
  requestAnimationFrame(draw);
}
function ws(){
  const s=new WebSocket((location.protocol==='https:'?'wss://':'ws://')+location.host+location.pathname.replace(/\\/$/,'')+'/ws/poses');
  s.onopen=()=>document.getElementById('status').textContent='live';
  s.onmessage=e=>{const m=JSON.parse(e.data);if(m.type==='pose'){(agents[m.agent]=agents[m.agent]||{traj:[],map:m.map_id}).pose=m.position;}};
  s.onclose=()=>{document.getElementById('status').textContent='reconnecting…';setTimeout(ws,2000);};
}
poll();ws();draw();
</script></body></html>
"""


@router.get("/", response_class=HTMLResponse, include_in_schema=False)
def viewer() -> str:
    return PAGE
