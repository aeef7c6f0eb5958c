// Stream queue scenarios of the `streams` suite (issue 33), driven by
// amqp091-go: selected with --streams, run by lib/streams.py against a
// RabbitMQ 3.10 node and a Leveret. Like python/s_streams.py, they record
// invariants where RabbitMQ's output depends on its storage layout (where
// `last` starts, offsets taken by segment headers, how much retention
// removes).
package main

import (
	"errors"
	"fmt"
	"strings"
	"time"

	amqp "github.com/rabbitmq/amqp091-go"
)

// refusal is [code, reply text] of a broker's close, the text cut before an
// Erlang term that ends it.
func refusal(err error) []interface{} {
	var e *amqp.Error
	if !errors.As(err, &e) {
		if err == nil {
			return nil
		}
		return []interface{}{"non-amqp error", err.Error()}
	}
	text := e.Reason
	if i := strings.LastIndex(text, ": "); i >= 0 {
		tail := text[i+2:]
		if strings.HasPrefix(tail, "{") || strings.HasPrefix(tail, "<<") || strings.HasPrefix(tail, "\"") || tail == "invalid_max_age" {
			text = text[:i]
		}
	}
	return []interface{}{e.Code, text}
}

func expectRefusal(t *T, label string, err error, code int) {
	got := refusal(err)
	t.Obs(label, got)
	if got == nil {
		t.Fatalf("%s: expected refusal %d, call succeeded", label, code)
	}
	if got[0] != code {
		t.Fatalf("%s: expected %d, got %v", label, code, got)
	}
}

var streamArgs = amqp.Table{"x-queue-type": "stream"}

func withStream(args amqp.Table) amqp.Table {
	out := amqp.Table{"x-queue-type": "stream"}
	for k, v := range args {
		out[k] = v
	}
	return out
}

// declareStream declares the stream t.N(name), deleted at the end.
func declareStream(t *T, name string, args amqp.Table) string {
	q := t.N(name)
	ch := channel(t, dial(t, "", nil))
	_, err := ch.QueueDeclare(q, true, false, false, false, withStream(args))
	t.Must(err, "declare stream")
	t.Defer(func() {
		if c, err := amqp.Dial(t.URL); err == nil {
			if ch, err := c.Channel(); err == nil {
				ch.QueueDelete(q, false, false, false)
			}
			c.Close()
		}
	})
	return q
}

// publishConfirmed publishes each body and waits for its confirm.
func publishConfirmed(t *T, q string, bodies []string) {
	ch := channel(t, dial(t, "", nil))
	confirms := confirmedPublisher(t, ch)
	for _, b := range bodies {
		publish(t, ch, "", q, b)
		if !awaitConfirms(t, confirms, 1)[0] {
			t.Fatalf("publish of %s nacked", b)
		}
	}
}

type streamReader struct {
	ch  *amqp.Channel
	ds  <-chan amqp.Delivery
	got []amqp.Delivery
	ack bool
}

// newReader consumes q from offset (nil: no x-stream-offset) with a prefetch.
func newReader(t *T, q string, offset interface{}, prefetch int, ack bool) *streamReader {
	ch := channel(t, dial(t, "", nil))
	t.Must(ch.Qos(prefetch, 0, false), "basic.qos")
	args := amqp.Table{}
	if offset != nil {
		args["x-stream-offset"] = offset
	}
	ds, err := ch.Consume(q, "", false, false, false, false, args)
	t.Must(err, "basic.consume")
	return &streamReader{ch: ch, ds: ds, ack: ack}
}

func (r *streamReader) take(d amqp.Delivery) {
	r.got = append(r.got, d)
	if r.ack {
		d.Ack(false)
	}
}

func (r *streamReader) until(t *T, n int) *streamReader {
	deadline := time.After(hang)
	for len(r.got) < n {
		select {
		case d, ok := <-r.ds:
			if !ok {
				t.Fatalf("deliveries ended after %d of %d", len(r.got), n)
			}
			r.take(d)
		case <-deadline:
			t.Fatalf("expected %d deliveries, got %d: %v", n, len(r.got), bodies(r.got))
		}
	}
	return r
}

// quiet takes whatever else arrives within d (what follows asserts that nothing did).
func (r *streamReader) quiet(d time.Duration) *streamReader {
	deadline := time.After(d)
	for {
		select {
		case dv, ok := <-r.ds:
			if !ok {
				return r
			}
			r.take(dv)
		case <-deadline:
			return r
		}
	}
}

func (r *streamReader) offsets() []interface{} {
	out := []interface{}{}
	for _, d := range r.got {
		out = append(out, d.Headers["x-stream-offset"])
	}
	return out
}

func seq(prefix string, from, n int) []string {
	out := []string{}
	for i := from; i < from+n; i++ {
		out = append(out, fmt.Sprintf("%s%d", prefix, i))
	}
	return out
}

func int64s(from, n int) []int64 {
	out := []int64{}
	for i := from; i < from+n; i++ {
		out = append(out, int64(i))
	}
	return out
}

func init() {
	streamScenario("declare.rules", func(t *T) {
		c := dial(t, "", nil)
		cases := []struct {
			label                          string
			name                           string
			durable, autoDelete, exclusive bool
		}{
			{"non-durable", t.N("nd"), false, false, false},
			{"exclusive", t.N("ex"), true, false, true},
			{"auto-delete", t.N("ad"), true, true, false},
			{"server-named", "", true, false, false},
		}
		for _, k := range cases {
			_, err := channel(t, c).QueueDeclare(k.name, k.durable, k.autoDelete, k.exclusive, false, streamArgs)
			expectRefusal(t, k.label, err, 406)
		}
		q := declareStream(t, "ok", amqp.Table{"x-max-age": "1D", "x-max-length-bytes": int64(1 << 30), "x-stream-max-segment-size-bytes": int32(1 << 20)})
		_, err := channel(t, c).QueueDeclare(q, true, false, false, false, nil)
		// Which inequivalent argument RabbitMQ names first is its own order: the code and name only.
		t.Obs("redeclared as classic", amqpErr(err))
		t.Check(len(amqpErr(err)) == 2 && amqpErr(err)[0] == 406, "redeclared as classic: expected 406, got %v", err)
		_, err = channel(t, c).QueueDeclare(t.N("bad"), true, false, false, false, withStream(amqp.Table{"x-max-age": "5 minutes"}))
		expectRefusal(t, "x-max-age '5 minutes'", err, 406)
	})

	streamScenario("offset.first_next_absolute", func(t *T) {
		q := declareStream(t, "forms", nil)
		publishConfirmed(t, q, seq("m", 0, 10))
		first := newReader(t, q, "first", 50, true).until(t, 10).quiet(500 * time.Millisecond)
		t.Eq("first", bodies(first.got), seq("m", 0, 10))
		t.Eq("offsets", first.offsets(), int64s(0, 10))
		abs := newReader(t, q, int64(7), 50, true).until(t, 3).quiet(500 * time.Millisecond)
		t.Eq("absolute 7", bodies(abs.got), seq("m", 7, 3))
		abs32 := newReader(t, q, int32(8), 50, true).until(t, 2).quiet(500 * time.Millisecond)
		t.Eq("absolute 8 as int32", abs32.offsets(), int64s(8, 2))
		next := newReader(t, q, "next", 50, true).quiet(500 * time.Millisecond)
		dflt := newReader(t, q, nil, 50, true).quiet(500 * time.Millisecond)
		t.Eq("next: nothing old", len(next.got), 0)
		publishConfirmed(t, q, []string{"n0"})
		t.Eq("next then", bodies(next.until(t, 1).quiet(500*time.Millisecond).got), []string{"n0"})
		t.Eq("no offset argument then", dflt.until(t, 1).quiet(500*time.Millisecond).offsets(), int64s(10, 1))
		t.Eq("first reader then", bodies(first.until(t, 11).quiet(500*time.Millisecond).got), append(seq("m", 0, 10), "n0"))
	})

	streamScenario("offset.last", func(t *T) {
		q := declareStream(t, "last", nil)
		publishConfirmed(t, q, seq("m", 0, 10))
		r := newReader(t, q, "last", 50, true).until(t, 1).quiet(time.Second)
		got := bodies(r.got)
		all := seq("m", 0, 10)
		tail := len(got) >= 1 && len(got) <= 10 && fmt.Sprint(got) == fmt.Sprint(all[10-len(got):])
		t.Eq("a contiguous tail ending at the last message", tail, true)
		publishConfirmed(t, q, []string{"n0"})
		r.until(t, len(got)+1).quiet(500 * time.Millisecond)
		t.Eq("then", bodies(r.got[len(got):]), []string{"n0"})
		t.Eq("its offset", r.offsets()[len(got):], int64s(10, 1))
	})

	streamScenario("offset.timestamp_and_interval", func(t *T) {
		q := declareStream(t, "ts", nil)
		publishConfirmed(t, q, seq("a", 0, 4))
		boundary := time.Now().Unix() + 1
		time.Sleep(time.Until(time.Unix(boundary, 300*int64(time.Millisecond))))
		publishConfirmed(t, q, seq("b", 0, 4))
		at := newReader(t, q, time.Unix(boundary, 0), 50, true).until(t, 4).quiet(500 * time.Millisecond)
		t.Eq("from the second boundary", bodies(at.got), seq("b", 0, 4))
		t.Eq("offsets", at.offsets(), int64s(4, 4))
		old := newReader(t, q, time.Unix(946684800, 0), 50, true).until(t, 8).quiet(500 * time.Millisecond)
		t.Eq("from 2000-01-01", bodies(old.got), append(seq("a", 0, 4), seq("b", 0, 4)...))
		ago := newReader(t, q, "10m", 50, true).until(t, 8).quiet(500 * time.Millisecond)
		t.Eq("from 10m ago", ago.offsets(), int64s(0, 8))
		ch := channel(t, dial(t, "", nil))
		t.Must(ch.Qos(10, 0, false), "basic.qos")
		_, err := ch.Consume(q, "", false, false, false, false, amqp.Table{"x-stream-offset": "10 minutes"})
		expectRefusal(t, "x-stream-offset '10 minutes'", err, 406)
	})

	streamScenario("offset.header_type", func(t *T) {
		q := declareStream(t, "hdr", nil)
		publishConfirmed(t, q, []string{"m0"})
		r := newReader(t, q, "first", 10, true).until(t, 1)
		v := r.got[0].Headers["x-stream-offset"]
		t.Eq("x-stream-offset header", fmt.Sprintf("%T %v", v, v), "int64 0")
		t.Eq("headers", len(r.got[0].Headers), 1)
	})

	streamScenario("consume.rules", func(t *T) {
		q := declareStream(t, "rules", nil)
		publishConfirmed(t, q, []string{"m0"})
		ch := channel(t, dial(t, "", nil))
		_, err := ch.Consume(q, "", false, false, false, false, nil)
		expectRefusal(t, "no prefetch", err, 406)
		ch = channel(t, dial(t, "", nil))
		t.Must(ch.Qos(10, 0, false), "basic.qos")
		_, err = ch.Consume(q, "", true, false, false, false, nil)
		expectRefusal(t, "auto-ack", err, 540)
		ch = channel(t, dial(t, "", nil))
		_, _, err = ch.Get(q, false)
		expectRefusal(t, "basic.get", err, 540)
	})

	streamScenario("consume.credit_and_acks_never_remove", func(t *T) {
		q := declareStream(t, "credit", nil)
		publishConfirmed(t, q, seq("m", 0, 8))
		r := newReader(t, q, "first", 2, false).until(t, 2).quiet(time.Second)
		t.Eq("prefetch 2, no acks", bodies(r.got), seq("m", 0, 2))
		t.Must(r.got[1].Ack(true), "ack multiple")
		r.until(t, 4).quiet(time.Second)
		t.Eq("after acking both", bodies(r.got), seq("m", 0, 4))
		for _, d := range r.got[2:] {
			t.Must(d.Ack(false), "ack")
		}
		r.ack = true
		r.until(t, 8).quiet(500 * time.Millisecond)
		again := newReader(t, q, "first", 100, true).until(t, 8).quiet(500 * time.Millisecond)
		t.Eq("a second reader after every ack", bodies(again.got), seq("m", 0, 8))
		t.Eq("same offsets", again.offsets(), r.offsets())
	})

	streamScenario("retention.max_length_bytes", func(t *T) {
		q := declareStream(t, "bytes", amqp.Table{"x-max-length-bytes": int64(2000), "x-stream-max-segment-size-bytes": int64(500)})
		sent := []string{}
		for i := 0; i < 60; i++ {
			sent = append(sent, fmt.Sprintf("m%03d%s", i, strings.Repeat("y", 46)))
		}
		publishConfirmed(t, q, sent)
		r := newReader(t, q, "first", 100, true)
		deadline := time.Now().Add(hang)
		for len(r.got) == 0 || string(r.got[len(r.got)-1].Body) != sent[59] {
			if time.Now().After(deadline) {
				t.Fatalf("never reached the last message: %v", bodies(r.got))
			}
			r.quiet(50 * time.Millisecond)
		}
		r.quiet(500 * time.Millisecond)
		kept := bodies(r.got)
		t.Eq("what remains is a tail ending with the last message", fmt.Sprint(kept) == fmt.Sprint(sent[60-len(kept):]), true)
		t.Eq("the oldest are gone", len(kept) < 60, true)
		first, _ := r.got[0].Headers["x-stream-offset"].(int64)
		t.Eq("the first offset moved", first > 0, true)
		size := 0
		for _, b := range kept {
			size += len(b)
		}
		t.Eq("at most max-length-bytes plus one segment kept", size <= 2000+500, true)
	})
}
