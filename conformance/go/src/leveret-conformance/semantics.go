// Scenarios of the `semantics` suite (issue 30) driven by amqp091-go:
// selected with --semantics, run by lib/semantics.py against a RabbitMQ
// 3.10 node and a Leveret loaded from semantics/definitions.json, with the
// broker's management API at --http. Like python/s_semantics.py's
// equivalence scenarios, from Go's side: a queue the definitions or the
// API made (JSON numbers), redeclared with integers of every width Go
// sends, is the same queue; another value is 406.
package main

import (
	"bytes"
	"encoding/json"
	"fmt"
	"net/http"
	"net/url"

	amqp "github.com/rabbitmq/amqp091-go"
)

// httpCall sends `body` (JSON, or nothing) to the management API and
// returns the status code.
func httpCall(t *T, method, path string, body interface{}) int {
	t.Check(t.HTTP != "", "the semantics scenarios need --http")
	var reader *bytes.Reader
	if body != nil {
		encoded, err := json.Marshal(body)
		t.Must(err, "encode")
		reader = bytes.NewReader(encoded)
	} else {
		reader = bytes.NewReader(nil)
	}
	req, err := http.NewRequest(method, t.HTTP+path, reader)
	t.Must(err, "request")
	req.SetBasicAuth(t.User, t.Password)
	req.Header.Set("content-type", "application/json")
	resp, err := http.DefaultClient.Do(req)
	t.Must(err, method+" "+path)
	resp.Body.Close()
	return resp.StatusCode
}

// declareOutcome is "ok" or the reply code of a durable queue's declare on
// a channel of its own.
func declareOutcome(t *T, c *amqp.Connection, queue string, args amqp.Table) interface{} {
	ch, err := c.Channel()
	t.Must(err, "channel")
	_, err = ch.QueueDeclare(queue, true, false, false, false, args)
	if err == nil {
		ch.Close()
		return "ok"
	}
	if e, ok := err.(*amqp.Error); ok {
		return e.Code
	}
	return err.Error()
}

func init() {
	semanticsScenario("equivalence.definitions_queue_redeclared_in_every_width", func(t *T) {
		// sem.defs.args as the definitions made it: ttl 60000, expires
		// 86400000, max-length 10, max-length-bytes 1048576, max-priority 5.
		c := dial(t, "", nil)
		defer c.Close()
		widths := []amqp.Table{
			{"x-message-ttl": int64(60000), "x-expires": int64(86400000), "x-max-length": int64(10),
				"x-max-length-bytes": int64(1048576), "x-max-priority": int64(5)},
			{"x-message-ttl": int32(60000), "x-expires": int32(86400000), "x-max-length": int8(10),
				"x-max-length-bytes": int32(1048576), "x-max-priority": byte(5)},
			{"x-message-ttl": int32(60000), "x-expires": int32(86400000), "x-max-length": int16(10),
				"x-max-length-bytes": int32(1048576), "x-max-priority": int16(5)},
		}
		rest := amqp.Table{"x-overflow": "reject-publish", "x-dead-letter-exchange": "sem.defs.dlx",
			"x-dead-letter-routing-key": "dead"}
		for i, args := range widths {
			for k, v := range rest {
				args[k] = v
			}
			t.Obs(fmt.Sprintf("widths %d", i), declareOutcome(t, c, "sem.defs.args", args))
		}
		other := amqp.Table{}
		for k, v := range widths[1] {
			other[k] = v
		}
		other["x-max-priority"] = int8(6)
		t.Obs("another max-priority", declareOutcome(t, c, "sem.defs.args", other))
	})

	semanticsScenario("equivalence.api_queue_redeclared_in_every_width", func(t *T) {
		q := t.N("go.api")
		path := "/api/queues/%2F/" + url.PathEscape(q)
		t.Defer(func() { httpCall(t, "DELETE", path, nil) })
		made := httpCall(t, "PUT", path, map[string]interface{}{"durable": true, "auto_delete": false,
			"arguments": map[string]interface{}{"x-message-ttl": 1000, "x-max-length": 7, "x-max-priority": 3}})
		t.Obs("API creates", made/100)
		c := dial(t, "", nil)
		defer c.Close()
		for i, args := range []amqp.Table{
			{"x-message-ttl": int16(1000), "x-max-length": int8(7), "x-max-priority": byte(3)},
			{"x-message-ttl": int64(1000), "x-max-length": int64(7), "x-max-priority": int64(3)},
			{"x-message-ttl": int32(1000), "x-max-length": int16(7), "x-max-priority": int8(3)},
		} {
			t.Obs(fmt.Sprintf("widths %d", i), declareOutcome(t, c, q, args))
		}
		t.Obs("another max-length", declareOutcome(t, c, q,
			amqp.Table{"x-message-ttl": int16(1000), "x-max-length": int8(8), "x-max-priority": byte(3)}))
	})
}
