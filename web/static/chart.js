// Learning curves as inline SVG: a few series on shared axes, with ticks, grid and a legend.
//
// drawChart(figure, {title, xLabel, yLabel, time, xInteger, xMin, xMax, yMin, yMax, note, series: [
//   {name, color, kind: "line" | "dots" | "bars", points: [[x, y], ...], barWidth}]})
// Points whose y is null or not a number are dropped ("draw what exists"). The drawing is as
// wide as its figure (in CSS pixels, so text keeps its size) and redrawn on every refresh.
// `xInteger`: x counts something (rounds), so its ticks are whole numbers and one point sits
// between its neighbours, not at -0.4 ... 0.4.

const H = 250;
const PAD = { left: 58, right: 14, top: 12, bottom: 38 };
const NS = "http://www.w3.org/2000/svg";
export const COLORS = ["#2457d6", "#d9822b", "#2f9e44", "#9c36b5", "#868e96"];

function svg(tag, attrs = {}, ...children) {
  const node = document.createElementNS(NS, tag);
  for (const [name, value] of Object.entries(attrs)) node.setAttribute(name, value);
  node.append(...children);
  return node;
}

/** About `count` round tick values (1, 2 or 5 times a power of ten) covering [lo, hi]. */
function ticks(lo, hi, count = 5) {
  const raw = (hi - lo) / count;
  const power = 10 ** Math.floor(Math.log10(raw));
  const step = power * ([1, 2, 5, 10].find((m) => m * power >= raw) ?? 10);
  const values = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) {
    values.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  }
  return { values, step };
}

/** 1500 -> "1.5k", 2e6 -> "2M", 0.25 -> "0.25". */
function compact(value) {
  const abs = Math.abs(value);
  if (abs >= 1e6) return `${+(value / 1e6).toPrecision(3)}M`;
  if (abs >= 1e3) return `${+(value / 1e3).toPrecision(3)}k`;
  return `${+value.toPrecision(3)}`;
}

function clock(ms) {
  return new Date(ms).toLocaleTimeString([], { hour: "2-digit", minute: "2-digit" });
}

function extent(values, fixedLo, fixedHi, integer = false) {
  let lo = fixedLo ?? Math.min(...values);
  let hi = fixedHi ?? Math.max(...values);
  if (lo === hi && integer) [lo, hi] = [lo - 1, hi + 1];
  else if (lo === hi) [lo, hi] = [lo - (Math.abs(lo) || 1) * 0.5, hi + (Math.abs(hi) || 1) * 0.5];
  return [lo, hi];
}

export function drawChart(figure, options) {
  const { title, xLabel = "", yLabel = "", time = false, note = "" } = options;
  const series = options.series
    .map((s, i) => ({
      color: COLORS[i % COLORS.length],
      kind: "line",
      ...s,
      points: s.points.filter(([x, y]) => Number.isFinite(x) && Number.isFinite(y)),
    }))
    .filter((s) => s.points.length > 0);

  const caption = document.createElement("figcaption");
  caption.append(title);
  if (note) caption.append(Object.assign(document.createElement("span"), {
    className: "chart-note", textContent: note,
  }));
  const plot = svg("svg", { role: "img", "aria-label": title });
  figure.replaceChildren(caption, plot);
  const W = Math.max(320, Math.round(plot.getBoundingClientRect().width) || 640);
  plot.setAttribute("viewBox", `0 0 ${W} ${H}`);
  if (series.length === 0) {
    plot.append(svg("text", { x: W / 2, y: H / 2, class: "empty" }, "No data yet"));
    return;
  }

  const all = series.flatMap((s) => s.points);
  const bars = series.filter((s) => s.kind === "bars");
  const barPad = Math.max(0, ...bars.map((s) => s.barWidth || 0));
  const [x0, x1] = extent(
    [...all.map(([x]) => x), ...all.map(([x]) => x + barPad)], options.xMin, options.xMax,
    options.xInteger);
  const yLo = options.yMin ?? (bars.length ? 0 : undefined);
  const [yDataLo, yDataHi] = extent(all.map(([, y]) => y), yLo, options.yMax);
  const yTicks = ticks(yDataLo, yDataHi);
  const y0 = Math.min(yDataLo, yTicks.values[0]);
  const y1 = Math.max(yDataHi, yTicks.values.at(-1));
  const sx = (x) => PAD.left + ((x - x0) / (x1 - x0)) * (W - PAD.left - PAD.right);
  const sy = (y) => H - PAD.bottom - ((y - y0) / (y1 - y0)) * (H - PAD.top - PAD.bottom);

  const grid = svg("g", { class: "grid" });
  for (const v of yTicks.values) {
    grid.append(svg("line", { x1: PAD.left, x2: W - PAD.right, y1: sy(v), y2: sy(v) }));
    grid.append(svg("text", { x: PAD.left - 6, y: sy(v) + 4, class: "tick y" }, compact(v)));
  }
  const xTicks = time ? timeTicks(x0, x1)
    : ticks(x0, x1).values.filter((v) => !options.xInteger || Number.isInteger(v));
  for (const v of xTicks) {
    grid.append(svg("line", { x1: sx(v), x2: sx(v), y1: H - PAD.bottom, y2: H - PAD.bottom + 4 }));
    grid.append(svg("text", { x: sx(v), y: H - PAD.bottom + 16, class: "tick x" },
      time ? clock(v) : compact(v)));
  }
  grid.append(svg("line", {
    class: "axis", x1: PAD.left, x2: W - PAD.right, y1: H - PAD.bottom, y2: H - PAD.bottom,
  }));
  grid.append(svg("text", { x: (PAD.left + W - PAD.right) / 2, y: H - 4, class: "label" }, xLabel));
  grid.append(svg("text", {
    x: 0, y: 0, class: "label", transform: `translate(12 ${(PAD.top + H - PAD.bottom) / 2}) rotate(-90)`,
  }, yLabel));
  plot.append(grid);

  for (const s of series) plot.append(drawSeries(s, sx, sy, y0, time, W));

  if (series.length > 1 || series[0].name) {
    const legend = document.createElement("div");
    legend.className = "legend";
    for (const s of series) {
      const item = document.createElement("span");
      item.innerHTML = `<i style="background:${s.color}"></i>`;
      item.append(s.name);
      legend.append(item);
    }
    figure.append(legend);
  }
}

function drawSeries(s, sx, sy, y0, time, W) {
  const group = svg("g", { fill: s.color, stroke: s.color });
  const tip = (x, y) => `${time ? clock(x) : compact(x)}: ${+y.toPrecision(4)}`;
  if (s.kind === "bars") {
    const width = Math.max(1, sx(s.points[0][0] + (s.barWidth || 1)) - sx(s.points[0][0]) - 1);
    for (const [x, y] of s.points) {
      group.append(svg("rect", {
        x: sx(x), y: sy(y), width, height: Math.max(0, sy(y0) - sy(y)), stroke: "none",
      }, svg("title", {}, tip(x, y))));
    }
    return group;
  }
  if (s.kind === "line" && s.points.length > 1) {
    const points = s.points.map(([x, y]) => `${sx(x).toFixed(1)},${sy(y).toFixed(1)}`).join(" ");
    group.append(svg("polyline", { points, fill: "none", "stroke-width": s.width || 2 }));
  }
  // Dots for dot series, and for short lines, where single points would otherwise vanish.
  if (s.kind === "dots" || s.points.length <= W / 16) {
    for (const [x, y] of s.points) {
      group.append(svg("circle", { cx: sx(x), cy: sy(y), r: 3, stroke: "none" },
        svg("title", {}, `${s.name ? `${s.name} ` : ""}${tip(x, y)}`)));
    }
  }
  return group;
}

/** Round clock times (1, 5, 15, 30 min, 1, 3, 6, 12 h, 1 day apart) across [t0, t1] in ms. */
function timeTicks(t0, t1) {
  const minute = 60_000;
  const steps = [1, 2, 5, 10, 15, 30, 60, 180, 360, 720, 1440].map((m) => m * minute);
  const step = steps.find((s) => (t1 - t0) / s <= 6) ?? steps.at(-1);
  const values = [];
  for (let t = Math.ceil(t0 / step) * step; t <= t1; t += step) values.push(t);
  return values;
}
